"""``python -m symcal`` runs the command line."""

import sys

from symcal.cli import main

sys.exit(main())
