"""``python -m ooi_seg_ros.cli`` == ``ooi-seg``."""

import sys

from . import main

sys.exit(main())
