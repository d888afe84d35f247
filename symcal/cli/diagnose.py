"""``symcal diagnose``: solve once, then show where the model fails and what is missing."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import data_map, data_options, inputs_of, out_lock, progress_of, write_stdout

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
    cmd.add_argument("--out", metavar="DIR",
                     help="write result.json (the solve), diagnosis.json and report.txt (the "
                          "solve's report and the diagnosis) to DIR, as one set")
    cmd.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    cmd.add_argument("--alpha", type=float, default=0.01,
                     help="family-wise significance level (default 0.01)")
    cmd.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Diagnose; print the findings; write plots and the HTML page when asked."""
    from symcal.base.files import check_output_folder, check_outputs
    from symcal.calibrate.solve import solve
    from symcal.problem.build import load_problem
    from symcal.report.plots import FORMATS

    if not 0 < args.alpha < 1:
        raise SymcalError(f"--alpha {args.alpha}: must lie between 0 and 1")
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    for fmt in formats:
        if fmt.lower() not in FORMATS:
            raise SymcalError(f"--format {fmt}: unknown plot format; choose from: "
                              f"{', '.join(FORMATS)}")
    problem = load_problem(args.problem)
    data = data_map(args)
    inputs = inputs_of(args, [problem])
    if args.plots:
        check_output_folder(args.plots, f"--plots {args.plots}")
    if args.report:
        check_outputs([args.report], inputs, f"--report {args.report}")
    if args.out:
        check_outputs([Path(args.out) / name for name in OUTPUTS], inputs, f"--out {args.out}")
    with out_lock(args.out, f"--out {args.out}"):
        lines, bars = progress_of(args)
        result = solve(problem, data, drop_invalid=args.drop_invalid, progress=lines,
                       bars=bars)
        return _diagnosed(args, result, formats, inputs)


def _diagnosed(args: argparse.Namespace, result: Any, formats: list[str], inputs: set[Path]
               ) -> int:
    """Diagnose a solved problem; print; write what was asked; the exit code."""
    from symcal.report.text import diagnosis_document, diagnosis_report, plain_json, text_report
    from symcal.revise.diagnose import diagnose

    diag = diagnose(result, alpha=args.alpha)
    text = diagnosis_report(diag)
    if not args.json:
        write_stdout(text)
    report = text_report(result) + "\n" + text
    if args.plots or args.report:
        _write(args, diagnosis_document(diag, series=True), report, formats, inputs)
    document = plain_json(diagnosis_document(diag))
    if args.out:
        _write_set(args.out, result, document, report, inputs)
    if args.json:
        write_stdout(document)
    return 0 if diag.result.success else 1


#: The set ``--out`` writes.
OUTPUTS = ("result.json", "diagnosis.json", "report.txt")


def _write_set(out: str, result: Any, document: str, report: str, inputs: set[Path]) -> None:
    """Write the result, the diagnosis and the report to ``out`` as one output set."""
    from symcal.base.files import OutputSet, atomic_write_text

    with OutputSet(out, inputs, f"--out {out}") as stage:
        result.save(stage / "result.json")
        atomic_write_text(stage / "diagnosis.json", document)
        atomic_write_text(stage / "report.txt", report)
    print(f"wrote {Path(out) / 'result.json'}, diagnosis.json and report.txt", file=sys.stderr)


def _write(args: argparse.Namespace, doc: dict, text: str, formats: list[str],
           inputs: set[Path]) -> None:
    """Write the figures (one output set in ``--plots``) and the HTML page."""
    from symcal.base.files import OutputSet

    if args.plots:
        from symcal.report.plots import save_figures

        with OutputSet(args.plots, inputs, f"--plots {args.plots}") as stage:
            written = save_figures(doc, stage, formats)
        print(f"wrote {sum(len(v) for v in written.values())} figure files to "
              f"{args.plots}", file=sys.stderr)
    if args.report:
        from symcal.report.html import write_html

        page = Path(args.report)
        with OutputSet(page.parent, inputs, f"--report {args.report}") as stage:
            write_html(doc, text, stage / page.name)
        print(f"wrote {page}", file=sys.stderr)
