"""`python -m compd` runs the command line."""

import sys

from compd.cli import main

sys.exit(main())
