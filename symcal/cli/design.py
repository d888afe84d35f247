"""``symcal design``: the predicted uncertainty of a planned motion, and a better motion."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import debug_option, inputs_of, out_lock, write_stdout

HELP = "predict the uncertainty of a planned motion and optimise it within its limits"

#: The files ``--out`` writes.
OUTPUTS = ("scenario.yaml", "report.txt", "motion.png")
#: IPOPT statuses that count as a solved design.
SOLVED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``design`` command to ``subparsers``."""
    cmd = subparsers.add_parser("design", help=HELP)
    cmd.add_argument("problem", help="problem YAML file")
    cmd.add_argument("--scenario", required=True, metavar="SCENARIO.yaml",
                     help="the system's truth, its noise and the planned motion")
    cmd.add_argument("--result", metavar="RESULT.json",
                     help="compare the predictions with the standard errors of this result")
    cmd.add_argument("--optimize", action="store_true",
                     help="choose the motion within the scenario's 'design' limits")
    cmd.add_argument("--criterion", choices=["D", "A", "E"],
                     help="minimise this criterion of the covariance (default D)")
    cmd.add_argument("--target", action="append", default=[], metavar="NAME=VALUE",
                     help="a standard-error target, e.g. l_x=5um (repeatable): met with the "
                          "fewest observations")
    cmd.add_argument("--seed", type=int, default=0,
                     help="seed of the poses the prediction is evaluated on (default 0)")
    cmd.add_argument("--out", metavar="DIR",
                     help="write scenario.yaml (the designed scenario), report.txt and "
                          "motion.png to DIR")
    cmd.add_argument("--json", action="store_true", help="print the design as JSON")
    debug_option(cmd)
    return cmd


def run(args: argparse.Namespace) -> int:
    """Predict (and with ``--optimize`` design); print the report or JSON; write ``--out``.

    Returns 0, or 1 when IPOPT did not solve the design.
    """
    from symcal.base.files import check_outputs, json_text
    from symcal.calibrate.result import Result
    from symcal.experiment.optimize import Design, design, parse_target
    from symcal.experiment.predict import predict
    from symcal.problem.build import load_problem
    from symcal.report.text import design_document, design_report
    from symcal.simulation import load_scenario

    if (args.target or args.criterion) and not args.optimize:
        raise SymcalError("--target and --criterion choose a motion: they need --optimize")
    if args.out and not args.optimize:
        raise SymcalError(f"--out {args.out} writes the optimised scenario: it needs "
                          "--optimize")
    if args.seed < 0:
        raise SymcalError(f"--seed {args.seed}: the seed must not be negative")
    problem = load_problem(args.problem)
    scenario = load_scenario(args.scenario)
    targets = tuple(parse_target(text, problem) for text in args.target)
    for target in targets:
        first = next(t for t in targets if t.name == target.name)
        if first is not target:
            raise SymcalError(f"--target {target.text}: a second target for '{target.name}' "
                              f"(the first is --target {first.text}); give one per parameter")
    inputs = inputs_of(args, [problem])
    option = f"--out {args.out}"
    if args.out:
        check_outputs([Path(args.out) / name for name in OUTPUTS], inputs, option)
    result = Result.load(args.result, problem) if args.result else None
    with out_lock(args.out, option):
        if args.optimize:
            outcome = design(problem, scenario, criterion=args.criterion, targets=targets,
                             seed=args.seed)
        else:
            base = predict(problem, scenario, seed=args.seed)
            outcome = Design(base, None, scenario, None, (), {}, {}, (), {}, "not optimised")
        path = str(Path(args.out) / "scenario.yaml") if args.out else None
        text = design_report(outcome, result)
        write_stdout(json_text(design_document(outcome, path)) if args.json else text)
        if args.out:
            _write(args, outcome, text, inputs, option)
            if not args.json:
                write_stdout(f"\nwrote {path}, report.txt and motion.png\n")
    solved = not args.optimize or outcome.message.startswith("only n") or any(
        outcome.message.endswith(s) for s in SOLVED)
    return 0 if solved else 1


def _write(args: argparse.Namespace, outcome: Any, text: str, inputs: set[Path],
           option: str) -> None:
    """Write the designed scenario, the report and the figure as one output set."""
    from symcal.base.files import OutputSet, atomic_write_text
    from symcal.report.plots import save_design_figure

    motions = {"given": outcome.poses(False, args.seed),
               "designed": outcome.poses(True, args.seed)}
    with OutputSet(args.out, inputs, option) as stage:
        atomic_write_text(stage / "scenario.yaml",
                          outcome.scenario_yaml(args.scenario, args.out))
        atomic_write_text(stage / "report.txt", text)
        save_design_figure(motions, stage / "motion.png", outcome.units)
