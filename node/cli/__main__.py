"""``python -m supramodal.node.cli``: the command line (as the ``supramodal`` script)."""

import sys

from supramodal.node.cli import main

sys.exit(main())
