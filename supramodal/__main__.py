"""``python -m supramodal``: the command line, where the ``supramodal`` script is not on PATH.

The one module of the model package that reaches the node: it runs the program, defines nothing
(tests/test_layers.py leaves ``__main__`` modules out for that reason).
"""

import sys

from supramodal.node.cli import main

sys.exit(main())
