"""``python -m recorder``: the recorder process."""

import sys

from recorder.service import main

sys.exit(main())
