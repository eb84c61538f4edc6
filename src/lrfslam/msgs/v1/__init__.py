"""Generated from schemas/lrfslam/msgs/v1 by ``python -m lrfslam.tools.gen_schemas`` (do not edit)."""
