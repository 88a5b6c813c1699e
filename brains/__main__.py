"""``python -m brains --brain NAME``: the brain host process."""

import sys

from brains.host import main

sys.exit(main())
