"""``python -m stellar_cal_ros``: the ``stellar-cal`` command line."""

import sys

from stellar_cal_ros.cli import main

sys.exit(main())
