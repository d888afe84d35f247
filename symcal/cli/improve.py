"""``symcal improve``: diagnose → add the top calibratable effect → re-solve → keep it if
the held-out residuals and BIC improve → repeat; every revision an overlay in ``--out``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import data_map, data_options, inputs_of, out_lock, progress_of

HELP = "improve the model round by round until the diagnosis is quiet"
#: The most rounds one run may take.
MAX_ROUNDS = 20


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``improve`` command to ``subparsers``."""
    cmd = subparsers.add_parser("improve", help=HELP, description=__doc__)
    cmd.add_argument("problem", help="problem YAML file (the starting model)")
    data_options(cmd)
    cmd.add_argument("--out", required=True, metavar="DIR",
                     help="folder for the revisions, final.yaml and the ladder")
    cmd.add_argument("--max-rounds", type=int, default=5, metavar="N",
                     help="keep at most N revisions (default 5)")
    cmd.add_argument("--alpha", type=float, default=0.01,
                     help="family-wise significance level of each diagnosis (default 0.01)")
    cmd.add_argument("--json", action="store_true", help="print the rounds as JSON")
    cmd.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Run the loop; write the ladder; print the rounds; exit 0 when the model is quiet."""
    from symcal.base.files import OutputSet, atomic_write_text, check_outputs
    from symcal.report.ladder import ladder_report, save_ladder_plot
    from symcal.report.text import (
        declared_gauges_line,
        floor_lines,
        noise_bias_line,
        outcome_text,
        plain_json,
        unvouched,
        unvouched_line,
    )
    from symcal.revise.improve import improve
    from symcal.revise.ladder import compare

    if not 1 <= args.max_rounds <= MAX_ROUNDS:
        raise SymcalError(f"--max-rounds {args.max_rounds}: must be between 1 and "
                          f"{MAX_ROUNDS}")
    if not 0 < args.alpha < 1:
        raise SymcalError(f"--alpha {args.alpha}: must lie between 0 and 1")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise SymcalError(f"--out {args.out}: exists and is not a folder")
    if any(p == out.resolve() or out.resolve() in p.parents for p in inputs_of(args)):
        raise SymcalError(f"--out {args.out}: an input file lies in it; choose a new folder")
    option = f"--out {args.out}"
    check_outputs([out / n for n in ("final.yaml", "ladder.txt", "ladder.json", "ladder.png")],
                  inputs_of(args), option)
    with out_lock(out, option):
        shown, bars = progress_of(args)
        result = improve(args.problem, out, data_map(args), args.max_rounds, args.alpha,
                         args.drop_invalid, shown, bars)
        rungs = compare([r.result for r in result.rounds])
        with OutputSet(out, inputs_of(args), option) as stage:
            atomic_write_text(stage / "ladder.txt", ladder_report(rungs))
            atomic_write_text(stage / "ladder.json", plain_json([r.to_dict() for r in rungs]))
            save_ladder_plot(rungs, stage)
    left, hints = _left(result, args.alpha)
    reach = unvouched(result.last)
    if args.json:
        sys.stdout.write(plain_json({**result.to_dict(), "left": left, "unvouched": [
            {"parameter": name, "reach_se": value if math.isfinite(value) else None,
             "absorbed": not math.isfinite(value)} for name, value in reach],
            "noise_bias": result.last.noise_bias_dict()}))
    else:
        lines = [f"symcal improve: {len(result.rounds) - 1} round(s) kept; "
                 + outcome_text(result), ""]
        lines += [f"  {line}" for line in floor_lines(result.rounds[-1].result)]
        lines += [f"  what is left above the floor: {line}" for line in left[:3]]
        lines += [f"  {line}" for line in hints]
        if reach:
            lines.append("  " + unvouched_line(reach, "symcal diagnose of the final problem "
                                                      "names them"))
        shifted = noise_bias_line(result.last)
        if shifted:
            lines.append("  " + shifted)
        declared = declared_gauges_line(result.last)
        if declared:
            lines.append("  " + declared)
        for r in result.rounds:
            what = r.added or "(the starting problem)"
            lines.append(f"  round {r.index}: {what}  [{r.problem_file}]")
            lines += [f"    {note}" for note in r.notes()]
        for (label, why), k in zip(result.rejected, result.tried_in(), strict=True):
            lines.append(f"  not kept{'' if k is None else f' (round {k})'}: {label}: {why}")
        for label, why in result.aliased:
            lines.append(f"  real but not calibratable by these constraints: {label}: {why}")
        lines += ["", ladder_report(rungs).rstrip(), "",
                  f"final problem: {result.final_problem}",
                  f"wrote the revisions, ladder.txt, ladder.json and ladder.png to {out}"]
        sys.stdout.write("\n".join(lines) + "\n")
    return 0 if result.verified and all(r.result.success for r in result.rounds) else 1


def _left(result: Any, alpha: float) -> tuple[list[str], tuple[str, ...]]:
    """Where the loop ends above the noise floor, what is left there (the last model's
    residuals along the variables their excess lies along, as ``symcal diagnose`` says
    it) and how to test a coupling it points at that no search space holds; else
    nothing."""
    from symcal.report.text import left_lines
    from symcal.revise.diagnose import diagnose

    last = result.rounds[-1].result
    if result.quiet or not last.success or last.at_floor is not False:
        return [], ()
    diag = diagnose(last, alpha)
    return left_lines(diag), diag.unsearched
