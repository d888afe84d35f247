"""``python -m symcal`` runs the command line."""

import sys

try:
    from symcal.cli import main
except KeyboardInterrupt:  # Ctrl-C while Python imports symcal: nothing has run yet
    sys.stderr.write("symcal: error: interrupted by SIGINT (Ctrl-C); no output was written "
                     "or changed\n")
    sys.exit(130)

sys.exit(main())
