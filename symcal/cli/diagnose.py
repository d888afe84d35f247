"""``symcal diagnose``: solve once, then show where the model fails and what is missing."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from symcal.cli.common import data_map, data_options, progress
from symcal.errors import SymcalError

HELP = "solve, then show where the model fails and which effect is missing"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``diagnose`` command to ``subparsers``."""
    cmd = subparsers.add_parser("diagnose", help=HELP)
    cmd.add_argument("problem", help="problem YAML file")
    data_options(cmd)
    cmd.add_argument("--plots", metavar="DIR", help="write the figures to DIR")
    cmd.add_argument("--format", default="png", metavar="FMT[,FMT]",
                     help="figure formats for --plots: png, svg, pdf (default png)")
    cmd.add_argument("--report", metavar="FILE.html", help="write one self-contained HTML "
                                                           "page")
    cmd.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    cmd.add_argument("--alpha", type=float, default=0.01,
                     help="family-wise significance level (default 0.01)")
    cmd.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Diagnose; print the findings; write plots and the HTML page when asked."""
    from symcal.calibrate import solve
    from symcal.diagnose import diagnose
    from symcal.plots import FORMATS
    from symcal.problem import load_problem
    from symcal.report import diagnosis_report, plain_json, text_report

    if not 0 < args.alpha < 1:
        raise SymcalError(f"--alpha {args.alpha}: must lie between 0 and 1")
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    for fmt in formats:
        if fmt.lower() not in FORMATS:
            raise SymcalError(f"--format {fmt}: unknown plot format; choose from: "
                              f"{', '.join(FORMATS)}")
    result = solve(load_problem(args.problem), data_map(args), drop_invalid=args.drop_invalid,
                   progress=None if args.quiet else progress)
    diag = diagnose(result, alpha=args.alpha)
    text = diagnosis_report(diag)
    if args.plots or args.report:
        doc = diag.to_dict(series=True)
        if args.plots:
            from symcal.plots import save_figures

            written = save_figures(doc, args.plots, formats)
            print(f"wrote {sum(len(v) for v in written.values())} figure files to "
                  f"{args.plots}", file=sys.stderr)
        if args.report:
            from symcal.htmlreport import write_html

            path = write_html(doc, text_report(result) + "\n" + text, args.report)
            print(f"wrote {path}", file=sys.stderr)
    sys.stdout.write(plain_json(diag.to_dict(series=False)) if args.json else text)
    return 0 if diag.result.success else 1
