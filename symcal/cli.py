"""Command-line interface: a thin argparse layer over the public API.

``main(argv)`` returns the exit code: 0 success, 1 failed solve, 2 bad input.  Errors are
printed as one message without a traceback unless ``--debug`` is given.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml

from symcal import cli_codegen
from symcal.errors import EXIT_BAD_INPUT, SymcalError


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors exit with symcal's bad-input code."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"symcal: error: {message}\n")


def _data_option(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH, found '{text}'")
    return name, path


def _data_options(parser: argparse.ArgumentParser) -> None:
    """The options every command that reads a problem's data shares."""
    parser.add_argument("--data", action="append", type=_data_option, default=[],
                        metavar="NAME=PATH", help="replace dataset NAME with a CSV/NPZ file")
    parser.add_argument("--drop-invalid", action="store_true",
                        help="drop rows with NaN/inf instead of refusing the data")
    parser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help=argparse.SUPPRESS)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="symcal", description="Autonomous calibration through sensor "
                                                "redundancy.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    solve = sub.add_parser("solve", help="calibrate a problem and print the report")
    solve.add_argument("problem", help="problem YAML file")
    _data_options(solve)
    solve.add_argument("--json", action="store_true", help="print the result as JSON")
    solve.add_argument("--out", metavar="DIR", help="write result.json and report.txt to DIR")
    solve.add_argument("--method", choices=["auto", "linear", "ipopt"],
                       help="solve every stage with this method (default: each stage's own, "
                            "auto = closed form when linear)")
    solve.add_argument("--weighting", choices=["equal", "estimated"],
                       help="weights of the constraints in the cost (default: the problem's; "
                            "estimated = by their residual covariance)")
    solve.add_argument("--max-iter", type=int, default=200, metavar="N",
                       help="iteration limit of IPOPT stages (default 200)")
    solve.add_argument("--quiet", action="store_true",
                       help="no progress on stderr and no report on success")

    diag = sub.add_parser("diagnose", help="solve, then show where the model fails and "
                                           "which effect is missing")
    diag.add_argument("problem", help="problem YAML file")
    _data_options(diag)
    diag.add_argument("--plots", metavar="DIR", help="write the figures to DIR")
    diag.add_argument("--format", default="png", metavar="FMT[,FMT]",
                      help="figure formats for --plots: png, svg, pdf (default png)")
    diag.add_argument("--report", metavar="FILE.html", help="write one self-contained HTML "
                                                            "page")
    diag.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    diag.add_argument("--alpha", type=float, default=0.01,
                      help="family-wise significance level (default 0.01)")
    diag.add_argument("--quiet", action="store_true", help="no progress on stderr")

    comp = sub.add_parser("compare", help="model revisions on the same data: the ladder")
    comp.add_argument("problems", nargs="+", help="problem YAML files, simplest first")
    _data_options(comp)
    comp.add_argument("--plots", metavar="DIR", help="write the ladder figure to DIR")
    comp.add_argument("--json", action="store_true", help="print the ladder as JSON")

    cli_codegen.add_parser(sub)

    sim = sub.add_parser("simulate", help="simulate a courier scenario to CSV")
    sim.add_argument("scenario", help="scenario YAML file")
    sim.add_argument("-o", "--output", required=True, metavar="OUT.csv",
                     help="output file (.csv or .npz); with several runs, OUT.<run>.csv")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--run", help="simulate only this run")
    sim.add_argument("-n", type=int, help="number of samples per run (overrides the scenario)")
    sim.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                     help=argparse.SUPPRESS)
    return parser


def _progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _inputs_of(args: argparse.Namespace) -> set[Path]:
    paths = {Path(args.problem).resolve()}
    paths |= {Path(p).resolve() for _, p in args.data}
    return paths


def _cmd_solve(args: argparse.Namespace) -> int:
    from symcal.calibrate import solve
    from symcal.data import atomic_write_text
    from symcal.problem import load_problem
    from symcal.report import json_report

    problem = load_problem(args.problem)
    data = dict(args.data)
    for name, _ in args.data:
        if list(data).count(name) > 1:
            raise SymcalError(f"--data {name}=... given twice")
    if args.max_iter < 1:
        raise SymcalError(f"--max-iter {args.max_iter}: must be at least 1")
    progress = None if args.quiet else _progress
    result = solve(problem, data, drop_invalid=args.drop_invalid, method=args.method,
                   progress=progress, max_iter=args.max_iter, weighting=args.weighting)
    text, doc = result.report(), json_report(result)
    if args.out:
        out = Path(args.out)
        inputs = _inputs_of(args) | {s.path for s in problem.datasets.values() if s.path}
        for target in (out / "result.json", out / "report.txt"):
            if target.resolve() in inputs:
                raise SymcalError(f"--out {args.out}: refusing to overwrite input file {target}")
            atomic_write_text(target, doc if target.suffix == ".json" else text)
    if not args.quiet or not result.success:
        sys.stdout.write(doc if args.json else text)
        if args.out and not args.json:
            sys.stdout.write(f"\nwrote {Path(args.out) / 'result.json'} and "
                             f"{Path(args.out) / 'report.txt'}\n")
    return 0 if result.success else 1


def _cmd_simulate(args: argparse.Namespace) -> int:
    from symcal.data import atomic_write_text, write_table
    from symcal.simulate import load_scenario, simulate_run, truth

    if args.n is not None and args.n < 1:
        raise SymcalError(f"-n {args.n}: the number of samples must be at least 1")
    if args.seed < 0:
        raise SymcalError(f"--seed {args.seed}: the seed must not be negative")
    scenario = load_scenario(args.scenario)
    runs = list(scenario.run_names)
    if args.run is not None:
        scenario.run_index(args.run)  # raises with a did-you-mean for an unknown run
        runs = [args.run]
    out = Path(args.output)
    if out.suffix.lower() not in (".csv", ".npz"):
        raise SymcalError(f"-o {args.output}: the output must end in .csv or .npz")
    if out.resolve() == Path(args.scenario).resolve():
        raise SymcalError(f"-o {args.output}: refusing to overwrite the scenario file")
    stem = out.with_suffix("")
    written = []
    for run in runs:
        target = out if len(runs) == 1 else stem.with_name(f"{stem.name}.{run}{out.suffix}")
        write_table(target, simulate_run(scenario, run, seed=args.seed, n=args.n))
        written.append(target)
    truth_path = stem.with_name(f"{stem.name}.truth.yaml")
    doc = truth(scenario)
    doc["seed"] = args.seed
    atomic_write_text(truth_path, yaml.safe_dump(doc, sort_keys=False))
    for target in written:
        print(f"wrote {target}")
    print(f"wrote {truth_path}")
    return 0


def _cmd_diagnose(args: argparse.Namespace) -> int:
    from symcal.diagnose import diagnose
    from symcal.report import plain_json

    if not 0 < args.alpha < 1:
        raise SymcalError(f"--alpha {args.alpha}: must lie between 0 and 1")
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    from symcal.plots import FORMATS

    for fmt in formats:
        if fmt.lower() not in FORMATS:
            raise SymcalError(f"--format {fmt}: unknown plot format; choose from: "
                              f"{', '.join(FORMATS)}")
    diag = diagnose(args.problem, dict(args.data), alpha=args.alpha,
                    progress=None if args.quiet else _progress,
                    drop_invalid=args.drop_invalid)
    text = diag.report()
    if args.plots or args.report:
        doc = diag.to_dict(series=True)
        if args.plots:
            from symcal.plots import save_figures

            written = save_figures(doc, args.plots, formats)
            print(f"wrote {sum(len(v) for v in written.values())} figure files to "
                  f"{args.plots}", file=sys.stderr)
        if args.report:
            from symcal.htmlreport import write_html

            path = write_html(doc, diag.result.report() + "\n" + text, args.report)
            print(f"wrote {path}", file=sys.stderr)
    sys.stdout.write(plain_json(diag.to_dict(series=False)) if args.json else text)
    return 0 if diag.result.success else 1


def _cmd_compare(args: argparse.Namespace) -> int:
    from symcal.ladder import compare, ladder_report, save_ladder_plot
    from symcal.report import plain_json

    rungs = compare(args.problems, dict(args.data), drop_invalid=args.drop_invalid)
    if args.plots:
        for path in save_ladder_plot(rungs, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    if args.json:
        sys.stdout.write(plain_json([r.to_dict() for r in rungs]))
    else:
        sys.stdout.write(ladder_report(rungs))
    return 0 if all(r.success for r in rungs) else 1


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    args = _parser().parse_args(argv)
    command = {"solve": _cmd_solve, "simulate": _cmd_simulate, "diagnose": _cmd_diagnose,
               "compare": _cmd_compare, "codegen": cli_codegen.run}[args.command]
    try:
        return command(args)
    except SymcalError as exc:
        if args.debug:
            raise
        print(f"symcal: error: {exc}", file=sys.stderr)
        return exc.exit_code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
