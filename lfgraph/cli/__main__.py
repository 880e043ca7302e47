"""``python -m lfgraph.cli``."""

import sys

from lfgraph.cli import main

sys.exit(main())
