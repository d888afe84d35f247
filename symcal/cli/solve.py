"""``symcal solve``: calibrate a problem and print (and optionally write) the report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from symcal.cli.common import data_map, data_options, inputs_of, progress
from symcal.errors import SymcalError

HELP = "calibrate a problem and print the report"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``solve`` command to ``subparsers``."""
    cmd = subparsers.add_parser("solve", help=HELP)
    cmd.add_argument("problem", help="problem YAML file")
    data_options(cmd)
    cmd.add_argument("--json", action="store_true", help="print the result as JSON")
    cmd.add_argument("--out", metavar="DIR", help="write result.json and report.txt to DIR")
    cmd.add_argument("--method", choices=["auto", "linear", "ipopt"],
                     help="solve every stage with this method (default: each stage's own, "
                          "auto = closed form when linear)")
    cmd.add_argument("--weighting", choices=["equal", "estimated"],
                     help="weights of the constraints in the cost (default: the problem's; "
                          "estimated = by their residual covariance)")
    cmd.add_argument("--max-iter", type=int, metavar="N",
                     help="iteration limit of IPOPT stages (default: the problem's, else "
                          "200)")
    cmd.add_argument("--quiet", action="store_true",
                     help="no progress on stderr and no report on success")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Solve; print the report or JSON; write ``--out``; return the exit code."""
    from symcal.calibrate import solve
    from symcal.files import atomic_write_text
    from symcal.language.options import MAX_ITER_LIMIT
    from symcal.problem import load_problem
    from symcal.report import json_report, text_report

    problem = load_problem(args.problem)
    data = data_map(args)
    if args.max_iter is not None and not 1 <= args.max_iter <= MAX_ITER_LIMIT:
        raise SymcalError(f"--max-iter {args.max_iter}: must be between 1 and "
                          f"{MAX_ITER_LIMIT}")
    if args.weighting:
        problem = problem.with_weighting(args.weighting)
    options = problem.options.over(method=args.method, max_iter=args.max_iter)
    result = solve(problem, data, options, drop_invalid=args.drop_invalid,
                   progress=None if args.quiet else progress)
    text, doc = text_report(result), json_report(result)
    if args.out:
        out = Path(args.out)
        inputs = inputs_of(args) | {s.path for s in problem.datasets.values() if s.path}
        inputs |= set(problem.source_files())
        for target in (out / "result.json", out / "report.txt"):
            if target.resolve() in inputs:
                raise SymcalError(f"--out {args.out}: refusing to overwrite input file {target}")
        result.save(out / "result.json")
        atomic_write_text(out / "report.txt", text)
    if not args.quiet or not result.success:
        sys.stdout.write(doc if args.json else text)
        if args.out and not args.json:
            sys.stdout.write(f"\nwrote {Path(args.out) / 'result.json'} and "
                             f"{Path(args.out) / 'report.txt'}\n")
    return 0 if result.success else 1
