"""``python -m services.noise``: the noise injector process."""

import sys

from services.noise.service import main

sys.exit(main())
