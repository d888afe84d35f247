"""``symcal compare``: model revisions solved on the same data, side by side."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from symcal.cli.common import data_map, data_options, inputs_of, write_stdout

HELP = "model revisions on the same data: the ladder"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``compare`` command to ``subparsers``."""
    cmd = subparsers.add_parser("compare", help=HELP)
    cmd.add_argument("problems", nargs="+", help="problem YAML files, simplest first")
    data_options(cmd)
    cmd.add_argument("--plots", metavar="DIR", help="write the ladder figure to DIR")
    cmd.add_argument("--json", action="store_true", help="print the ladder as JSON")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Solve every revision once on the first one's data; print the ladder; write its figure."""
    from symcal.base.files import OutputSet, check_output_folder
    from symcal.calibrate.solve import solve
    from symcal.data.loading import load_datasets
    from symcal.problem.build import load_problem
    from symcal.report.ladder import ladder_report, save_ladder_plot
    from symcal.report.text import plain_json
    from symcal.revise.ladder import compare

    problems = [load_problem(path) for path in args.problems]
    data = data_map(args)
    inputs = inputs_of(args, problems)
    option = f"--plots {args.plots}"
    if args.plots:
        check_output_folder(args.plots, option)
    datasets = load_datasets(problems[0], data, args.drop_invalid)
    results = [solve(p, {k: v for k, v in datasets.items() if k in p.datasets})
               for p in problems]
    rungs = compare(results)
    if not args.json:
        write_stdout(ladder_report(rungs))
    if args.plots:
        with OutputSet(args.plots, inputs, option) as stage:
            written = save_ladder_plot(rungs, stage)
        for path in written:
            print(f"wrote {Path(args.plots) / path.name}", file=sys.stderr)
    if args.json:
        write_stdout(plain_json([r.to_dict() for r in rungs]))
    return 0 if all(r.success for r in rungs) else 1
