"""The ROS 2 bridge: a run's camera, pose, clock and commands as a ROS 2 node on rmw_zenoh's keys."""
