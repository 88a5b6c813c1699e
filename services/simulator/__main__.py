"""``python -m services.simulator``: the simulator process."""

import sys

from services.simulator.service import main

sys.exit(main())
