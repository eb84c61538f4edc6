"""Generated from schemas/lrfslam/msgs/v1 by tools/gen_schemas (do not edit)."""
