"""``symcal codegen``: export the calibrated model as C99 (:func:`symcal.export.c.generate`)."""

from __future__ import annotations

import argparse
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import debug_option, inputs_of

HELP = "export the calibrated model as C99 (residuals, Jacobian, sensor outputs)"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``codegen`` subcommand to ``subparsers`` and return its parser."""
    cmd = subparsers.add_parser(
        "codegen", help=HELP,
        description="Write self-contained C99 for one observation: the residuals g(theta, "
                    "u) with their Jacobian, and each sensor instance's calibrated outputs, "
                    "behind a readable header, with an example main and a Makefile.")
    cmd.add_argument("problem", help="problem YAML file")
    cmd.add_argument("--result", metavar="RESULT.json",
                     help="bake in the parameters of this result ('symcal solve --out DIR' "
                          "writes DIR/result.json); without it the parameters are an "
                          "argument of every function")
    cmd.add_argument("-o", "--output", required=True, metavar="DIR",
                     help="output directory (created if absent)")
    cmd.add_argument("--force", action="store_true",
                     help="replace files in DIR that symcal did not write (e.g. your own "
                          "Makefile or main.c); input files are never replaced")
    debug_option(cmd)
    return cmd


def run(args: argparse.Namespace) -> int:
    """Generate the code; print one ``wrote PATH`` line per file; return the exit code."""
    from symcal.base.files import input_refusal
    from symcal.export.c import generate
    from symcal.problem.build import load_problem

    problem = load_problem(args.problem)
    if args.result:
        reason = input_refusal(args.result, MAX_RESULT_BYTES)
        if reason is not None:
            raise SymcalError(f"--result {args.result}: cannot read the result file: it "
                              f"{reason}")
    inputs = inputs_of(args, [problem])
    for path in generate(problem, args.output, args.result, args.force, inputs):
        print(f"wrote {path}")
    return 0


#: Largest result file read, in bytes.
MAX_RESULT_BYTES = 1 << 28
