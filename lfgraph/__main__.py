"""``python -m lfgraph``."""

import sys

from lfgraph.cli import main

sys.exit(main())
