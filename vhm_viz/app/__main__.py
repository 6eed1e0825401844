"""``python -m vhm_viz.app [FILE] [--scene SCENE]``: open the explorer."""

import sys

from vhm_viz.app import main

sys.exit(main())
