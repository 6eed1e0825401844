"""``python -m vhm_viz.cli``: the ``vhm-viz`` command line."""

import sys

from vhm_viz.cli import main

sys.exit(main())
