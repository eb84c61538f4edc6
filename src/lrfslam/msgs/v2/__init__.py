"""Generated from schemas/lrfslam/msgs/v2 by ``python -m lrfslam.tools.gen_schemas`` (do not edit)."""
