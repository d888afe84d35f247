"""``symcal design``: the predicted uncertainty of a planned motion, and a better motion."""

from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import debug_option, inputs_of, out_lock, write_stdout

HELP = "predict the uncertainty of a planned motion and optimise it within its limits"

#: The files ``--out`` writes.
OUTPUTS = ("scenario.yaml", "report.txt", "motion.png")


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
                     help="a standard-error target, e.g. l_x=5um, or a term to make "
                          "detectable at an amplitude, e.g. 'mde(s1.p_hat += harmonic 5 of "
                          "s1.p)=1um' (a candidate as symcal diagnose names it, or the "
                          "coefficients of a term in the problem: 'mde(s1.h5_sin, "
                          "s1.h5_cos)=1um'); repeatable, met with the fewest observations")
    cmd.add_argument("--hold", action="store_true",
                     help="with --target: hold every other parameter at its standard error "
                          "on the given motion (each is a further target), so that the "
                          "design makes none less precise")
    cmd.add_argument("--alpha", type=float, default=0.01,
                     help="with an mde(...) target: the family-wise level of the "
                          "diagnosis that is to detect the term, as symcal diagnose's "
                          "(default 0.01)")
    cmd.add_argument("--seed", type=int, default=0,
                     help="seed of the poses the prediction is evaluated on, and of the noise "
                          "of the data an mde(...) target is diagnosed on (default 0)")
    cmd.add_argument("--out", metavar="DIR",
                     help="write scenario.yaml (the designed scenario), report.txt and "
                          "motion.png to DIR")
    cmd.add_argument("--json", action="store_true", help="print the design as JSON")
    debug_option(cmd)
    return cmd


def run(args: argparse.Namespace) -> int:
    """Predict (and with ``--optimize`` design); print the report or JSON; write ``--out``.

    Returns 0, or 1 when IPOPT did not solve the design and it does not meet every
    target (and hold) on the exact prediction.
    """
    from symcal.base.files import check_outputs, json_text
    from symcal.calibrate.result import Result
    from symcal.experiment.detectable import parse_mde
    from symcal.experiment.optimize import HOLD_NEEDS_TARGET, Design, design, parse_target
    from symcal.experiment.predict import predict
    from symcal.problem.build import load_problem
    from symcal.report.text import design_document, design_report
    from symcal.simulation import load_scenario

    if (args.target or args.criterion) and not args.optimize:
        raise SymcalError("--target and --criterion choose a motion: they need --optimize")
    if args.hold and not args.target:
        raise SymcalError(HOLD_NEEDS_TARGET)
    if not 0 < args.alpha < 1:
        raise SymcalError(f"--alpha {args.alpha}: must lie between 0 and 1")
    if args.out and not args.optimize:
        raise SymcalError(f"--out {args.out} writes the optimised scenario: it needs "
                          "--optimize")
    if args.seed < 0:
        raise SymcalError(f"--seed {args.seed}: the seed must not be negative")
    problem = load_problem(args.problem)
    scenario = load_scenario(args.scenario)
    terms = [m for m in (parse_mde(text) for text in args.target) if m is not None]
    if len(terms) > 1:
        raise SymcalError(f"--target {terms[1].text}: a second term to make detectable (the "
                          f"first is --target {terms[0].text}); give one mde(...) target")
    targets = tuple(parse_target(text, problem) for text in args.target
                    if parse_mde(text) is None)
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
    with out_lock(args.out, option), tempfile.TemporaryDirectory(prefix="symcal-term-") as work:
        detect = (_detectable(terms[0], problem, scenario, args.seed, args.alpha, Path(work))
                  if terms else None)
        if args.optimize:
            outcome = design(problem, scenario, criterion=args.criterion, targets=targets,
                             seed=args.seed, detect=detect, hold=args.hold)
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
    # IPOPT stopped early, but its design meets every target on the exact prediction:
    # a usable design (the report says fewer observations may do)
    return 0 if outcome.converged or outcome.all_met else 1


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


def _simulated(problem: Any, scenario: Any, seed: int) -> dict[str, Any]:
    """Data for every dataset of ``problem`` simulated from ``scenario`` (noise drawn): the
    fitted one from the design run, another from the run of its name (else the design
    run again, with another seed)."""
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import needed_columns
    from symcal.experiment.predict import design_run
    from symcal.simulation import simulate_run

    run = design_run(problem, scenario)
    out = {}
    for k, name in enumerate(problem.datasets):
        which = name if name != problem.fit_dataset and name in scenario.run_names else run
        columns = simulate_run(scenario, which, seed + (0 if which != run else k))
        out[name] = make_dataset(name, f"{scenario.name} run '{which}'", columns,
                                 needed_columns(problem))
    return out


def _label(text: str) -> str:
    """A candidate's label as it is compared: spaces normalised, its period left out."""
    return re.sub(r"\s*\(period [^)]*\)", "", " ".join(text.split()))


def _detectable(parsed: Any, problem: Any, scenario: Any, seed: int, alpha: float,
                work: Path) -> Any:
    """The term of an ``mde(...)`` target, resolved as symcal diagnose would name and test
    it: a diagnosis of data simulated from the scenario gives the candidate (its shape and
    scales), the number of candidates tested (the level ``alpha / tested``), and the
    revised problem that has its coefficients (written into ``work``)."""
    from symcal.analysis.discovery import STANDALONE
    from symcal.base.didyoumean import did_you_mean
    from symcal.calibrate.solve import solve
    from symcal.experiment.detectable import (
        Detectable,
        amplitude,
        check_coefficients,
        coefficient_scales,
    )
    from symcal.experiment.predict import design_run
    from symcal.revise.diagnose import diagnose
    from symcal.revise.effects import revised_problem

    names = parsed.coefficients
    if names is not None:
        check_coefficients(problem, names, parsed.text)
    result = solve(problem, _simulated(problem, scenario, seed))
    if not result.success:
        raise SymcalError(f"--target {parsed.text}: the problem does not solve on data "
                          f"simulated from scenario '{scenario.name}', so no diagnosis says "
                          "which terms it tests; solve it first")
    diag = diagnose(result, alpha=alpha)
    tested = max(diag.tested, 1)
    if names is not None:
        scales, unit = coefficient_scales(problem, scenario, names, design_run(problem,
                                                                                scenario), seed)
        value, shown = amplitude(parsed, unit)
        return Detectable(f"the term of {', '.join(names)}", problem, names, scales,
                          alpha / tested, value, shown, parsed.text, alpha, tested)
    wanted = _label(parsed.term)
    found = [c for c in diag.candidates if _label(c.label) == wanted]
    if not found:
        labels = sorted({_label(c.label) for c in diag.candidates
                         if c.basis.kind not in STANDALONE})
        raise SymcalError(f"--target {parsed.text}: symcal diagnose tests no candidate "
                          f"'{parsed.term}' on this problem{did_you_mean(wanted, labels)}")
    cand = found[0]
    if cand.basis.kind in STANDALONE or len(cand.basis.scales) != len(cand.basis.columns):
        raise SymcalError(f"--target {parsed.text}: '{cand.label}' is not a term with an "
                          "amplitude")
    if cand.absorbed:
        biases = f" (it moves {', '.join(cand.biases)})" if cand.biases else ""
        raise SymcalError(f"--target {parsed.text}: on the given motion the parameters the "
                          f"problem has absorb {cand.label}{biases}; no test can see it")
    revised = revised_problem(problem, cand, work)
    added = tuple(n for n in revised.parameter_names if n not in problem.index)
    if len(added) != len(cand.basis.scales):
        raise SymcalError(f"--target {parsed.text}: the revision of '{cand.label}' adds "
                          f"{len(added)} parameters, not one per column of the term")
    check_coefficients(revised, added, parsed.text)
    output = next((q.unit for q in problem.signals if q.name == cand.output), "")
    value, shown = amplitude(parsed, output)
    return Detectable(cand.label, revised, added, tuple(float(x) for x in cand.basis.scales),
                      alpha / tested, value, shown, parsed.text, alpha, tested,
                      float(cand.basis.term))
