"""Views of the pipeline's messages for viewers: lrfslam messages in, a viewer's messages out.

No transport, no clock: the recorder, ``lrfslam export --foxglove`` and ``lrfslam monitor``
feed the same conversion, so a recording and the live view show the same thing.
"""
