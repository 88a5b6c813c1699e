"""``python -m services.viz``: the live view process (Foxglove WebSocket)."""

import sys

from services.viz.service import main

sys.exit(main())
