"""The ``ros2`` brain: a ROS 2 node (through rmw_zenoh's keys) drives."""
