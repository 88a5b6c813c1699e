"""``python -m services.ros2_bridge``: the ROS 2 bridge process."""

import sys

from services.ros2_bridge.service import main

sys.exit(main())
