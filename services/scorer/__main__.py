"""``python -m services.scorer``: the scorer process."""

import sys

from services.scorer.service import main

sys.exit(main())
