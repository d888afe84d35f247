"""``symcal solve``: calibrate a problem and print (and optionally write) the report."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from symcal.base.errors import SymcalError
from symcal.cli.common import (
    data_map,
    data_options,
    inputs_of,
    out_lock,
    progress_of,
    write_stdout,
)

if TYPE_CHECKING:
    from symcal.calibrate.result import Result

HELP = "calibrate a problem and print the report"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``solve`` command to ``subparsers``."""
    cmd = subparsers.add_parser("solve", help=HELP)
    cmd.add_argument("problem", help="problem YAML file")
    data_options(cmd)
    cmd.add_argument("--json", action="store_true", help="print the result as JSON")
    cmd.add_argument("--out", metavar="DIR", help="write result.json and report.txt to DIR")
    cmd.add_argument("--method", choices=["auto", "linear", "ipopt", "lm"],
                     help="solve every stage with this method (default: each stage's own, "
                          "auto = closed form when linear, else lm)")
    cmd.add_argument("--weighting", choices=["equal", "estimated", "propagated"],
                     help="weights of the constraints in the cost (default: the problem's; "
                          "estimated = by their residual covariance; propagated = by the "
                          "covariance the readings' declared noise gives them)")
    cmd.add_argument("--max-iter", type=int, metavar="N",
                     help="iteration limit of lm and IPOPT stages (default: the problem's, else "
                          "200)")
    cmd.add_argument("--quiet", action="store_true",
                     help="no progress on stderr and no text report on success (--json "
                          "still prints its document)")
    fleet = cmd.add_argument_group(
        "fleet", "calibrate every unit of a fleet folder in parallel on Dask: one "
                 "subfolder per unit holding NAME.csv, NAME.npz or NAME.parquet for the "
                 "problem's datasets NAME it has (the others come from --data or the "
                 "problem); --out DIR writes DIR/UNIT/result.json and report.txt for each "
                 "unit and DIR/fleet.json, fleet.txt, fleet.png; exit code 0 when every "
                 "unit solved, 1 when any unit failed (its reason is in the summary; the "
                 "other units are still solved), 2 for bad input of the fleet as a whole")
    fleet.add_argument("--fleet", metavar="DIR",
                       help="calibrate every unit of the fleet folder DIR")
    fleet.add_argument("--scheduler", metavar="ADDRESS",
                       help="use the running Dask scheduler at ADDRESS (e.g. "
                            "tcp://host:8786) instead of a local cluster")
    fleet.add_argument("--workers", type=int, metavar="N",
                       help="worker processes of the local cluster (default: one per core)")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Solve; print the report or JSON; write ``--out``; return the exit code.

    ``--out`` is checked before the solve (a folder that can be written, no input and no
    file symcal did not write replaced); ``result.json`` and ``report.txt`` then replace
    their predecessors together (:class:`symcal.base.files.OutputSet`).  Text reports are
    printed before they are written, so a failed write never loses them.
    """
    from symcal.base.files import check_outputs
    from symcal.base.options import MAX_ITER_LIMIT
    from symcal.problem.build import load_problem

    if args.max_iter is not None and not 1 <= args.max_iter <= MAX_ITER_LIMIT:
        raise SymcalError(f"--max-iter {args.max_iter}: must be between 1 and "
                          f"{MAX_ITER_LIMIT}")
    if args.fleet is not None:
        from symcal.cli.fleet import run_fleet

        return run_fleet(args)
    for option in ("scheduler", "workers"):
        if getattr(args, option) is not None:
            raise SymcalError(f"--{option} applies only with --fleet DIR")
    problem = load_problem(args.problem)
    data = data_map(args)
    inputs = inputs_of(args, [problem])
    option = f"--out {args.out}"
    if args.out:
        check_outputs([Path(args.out) / name for name in OUTPUTS], inputs, option)
    if args.weighting:
        problem = problem.with_weighting(args.weighting)
    with out_lock(args.out, option):
        return _solve(args, problem, data, inputs, option)


def _solve(args: argparse.Namespace, problem: Any, data: dict[str, str], inputs: set[Path],
           option: str) -> int:
    """Solve, print, write (while holding the lock of ``--out``); the exit code."""
    from symcal.calibrate.solve import solve
    from symcal.report.text import json_report, text_report

    options = problem.options.over(method=args.method, max_iter=args.max_iter)
    fit = problem.fit_dataset
    lines, bars = progress_of(args)
    if fit in data and Path(data[fit]).is_dir():      # a log kept as shards
        from symcal.calibrate.partitioned import solve_partitioned

        if args.drop_invalid:
            raise SymcalError(f"--drop-invalid does not apply to the folder of shards "
                              f"{data[fit]}: every shard's needed columns must be finite")
        result = solve_partitioned(problem, data[fit], options,
                                   data={k: v for k, v in data.items() if k != fit},
                                   progress=lines, bars=bars)
    else:
        result = solve(problem, data, options, drop_invalid=args.drop_invalid,
                       progress=lines, bars=bars)
    text = text_report(result)
    show = not args.quiet or not result.success
    if args.json:  # the document always, whatever --quiet says
        doc = json_report(result)
        if args.out:
            _write(args.out, result, text, inputs, option)
        write_stdout(doc)
        return 0 if result.success else 1
    if show:
        write_stdout(text)
    if args.out:
        _write(args.out, result, text, inputs, option)
        if show:
            write_stdout(f"\nwrote {Path(args.out) / 'result.json'} and "
                         f"{Path(args.out) / 'report.txt'}\n")
    return 0 if result.success else 1


#: The result set ``--out`` writes.
OUTPUTS = ("result.json", "report.txt")


def _write(out: str, result: Result, text: str, inputs: set[Path], option: str) -> None:
    """Write ``result.json`` and ``report.txt`` to ``out`` as one output set."""
    from symcal.base.files import OutputSet, atomic_write_text

    with OutputSet(out, inputs, option) as stage:
        result.save(stage / "result.json")
        atomic_write_text(stage / "report.txt", text)
