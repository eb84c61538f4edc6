"""The five processes of the pipeline, one module each (installed as lrfslam.services)."""
