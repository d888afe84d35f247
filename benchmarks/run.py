"""symcal's benchmark harness: symcal against what a user would write instead.

Run from the repository root (``make bench`` does)::

    .venv/bin/python benchmarks/run.py            # full run -> benchmarks/RESULTS.md
    .venv/bin/python benchmarks/run.py --quick    # every job at a tiny N; prints, writes nothing

The harness itself is the package ``benchmarks/bench`` (see its ``__init__``); this file
is its entry point, for the parent run and for every child process (``--child``).  See
benchmarks/README.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench.cli import main  # noqa: E402  (benchmarks/ is not installed)

if __name__ == "__main__":
    sys.exit(main())
