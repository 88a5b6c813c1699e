"""ROS 2 interoperability without ROS 2: interface definitions and their REP-2016 type hashes (``interfaces``), CDR
(``cdr``) and drivebench's messages as standard ROS 2 messages (``messages``). Pure Python: the bag exporter
(``recorder.ros2bag``) and the rmw_zenoh bridge share it. ``reference/ros2.md`` has the formats."""
