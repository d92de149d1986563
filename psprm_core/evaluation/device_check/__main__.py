"""``python -m psprm_core.evaluation.device_check``: :func:`.check.main`."""

import sys

from .check import main

sys.exit(main())
