"""ROS 2 over Zenoh (rmw_zenoh), without ROS: its wire format and lrfslam's messages as ROS messages.

Pure: key expressions, liveliness tokens, attachments and conversions, no session and no clock;
``lrfslam ros2`` (src/lrfslam/tools/ros2.py) puts them on the bus. docs/ros2.md.
"""
