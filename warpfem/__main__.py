"""``python -m warpfem``: the command line."""

import sys

from warpfem.cli import main

sys.exit(main())
