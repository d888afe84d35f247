"""Options, the run itself, and what it prints and writes."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .analysis import exponents, targets
from .config import DEFAULT_SIZES, HERE, LABELS, MARK, PROBLEMS, QUICK_SIZES, Run, Settings
from .fmt import fmt_n, say, show
from .jobs import CHILDREN, JOBS
from .jobs.base import JobSummary
from .machine import code_state, load_average, machine
from .measure import Clock
from .problems import check_residuals, make_data
from .report import atomic_write, method_table, render, splice, write_json


def child_main(spec: str) -> int:
    """The child's side of :mod:`bench.children`: run the job described by the JSON
    ``spec``, print its result."""
    job = json.loads(spec)
    result = CHILDREN[job["kind"]](job)
    sys.stdout.flush()
    print(MARK + json.dumps(result), flush=True)
    return 0


DESCRIPTION = """symcal's benchmark harness: symcal against what a user would write instead.

For the §3.1 linear problem and the §3.2 dual problem, on the same simulated data, at
each N it times symcal's default path and the peers of ``benchmarks/bench/peers.py``,
each (method, N) in a fresh subprocess, and writes the tables to ``--out``.  ``--quick``
runs every job at a tiny N and prints the tables instead.  See benchmarks/README.md.
"""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line of ``benchmarks/run.py``."""
    parser = argparse.ArgumentParser(description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: every job at N = 200, one run each, seconds in "
                             "all; prints the tables and writes nothing unless --out")
    parser.add_argument("--sizes", help="comma-separated N, e.g. 1e3,1e4 "
                                        "(default 1e3,1e4,1e5,1e6)")
    parser.add_argument("--repeats", type=int, help="runs per (method, N) below 1e6 "
                                                    "(default 3; 1 with --quick)")
    parser.add_argument("--cap", type=float, help="skip a peer whose projected time "
                                                  "exceeds this (s, default 120; 10 with "
                                                  "--quick)")
    parser.add_argument("--repeat-budget", type=float, default=20.0,
                        help="stop repeating once the runs would pass this (s, default 20)")
    parser.add_argument("--budget", type=float, default=12.5,
                        help="wall-clock budget of the whole run in minutes: capped rows "
                             "are skipped or stopped to stay within it (default 12.5)")
    parser.add_argument("--blas-threads", default="1",
                        help="BLAS threads in every timed process ('default' leaves the "
                             "library's choice; default 1)")
    parser.add_argument("--out", help="where to write the tables (default "
                                      "benchmarks/RESULTS.md; none with --quick)")
    parser.add_argument("--json", help="also write the raw measurements here")
    parser.add_argument("--jobs", help="comma-separated jobs to run (default: all; "
                                       f"{', '.join(j.NAME for j in JOBS)}); with --out, "
                                       "the sections of the jobs that ran replace theirs "
                                       "in the existing file and the others are kept")
    parser.add_argument("--methods", help="comma-separated methods of the solve job "
                                          "(default: all)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def settings_from(args: argparse.Namespace) -> Settings:
    """The run's settings from the command line."""
    if args.sizes:
        sizes = tuple(sorted({int(float(s)) for s in args.sizes.split(",") if s.strip()}))
    else:
        sizes = QUICK_SIZES if args.quick else DEFAULT_SIZES
    if not sizes or min(sizes) < 10:
        raise SystemExit("--sizes: give observation counts of at least 10")
    out = args.out or (None if args.quick else str(HERE / "RESULTS.md"))
    known = {j.NAME for j in JOBS}
    jobs = tuple(j.strip() for j in (args.jobs or "").split(",") if j.strip())
    if set(jobs) - known:
        raise SystemExit(f"--jobs: unknown {sorted(set(jobs) - known)}; jobs: "
                         f"{', '.join(sorted(known))}")
    if jobs and "starts" not in jobs and {"solve", "blas", "profile"} & set(jobs):
        jobs = ("starts", *jobs)        # the common start every solve needs
    methods = tuple(m.strip() for m in (args.methods or "").split(",") if m.strip())
    if set(methods) - set(LABELS):
        raise SystemExit(f"--methods: unknown {sorted(set(methods) - set(LABELS))}")
    return Settings(sizes, args.repeats or (1 if args.quick else 3),
                    args.cap or (10.0 if args.quick else 120.0), args.repeat_budget,
                    60 * args.budget,
                    None if args.blas_threads == "default" else args.blas_threads,
                    None if out is None else Path(out), args.quick, jobs, methods)


def _console_summary(report: dict[str, Any], settings: Settings) -> None:
    say("\n== fitted exponent of time vs N (all sizes; N >= 1e4; time per pass, N >= 1e4):")
    for (problem, method), (a_all, a_big, a_pass) in exponents(
            report.get("rows", [])).items():
        say(f"  {problem:6s} {LABELS[method]:44s} {show(a_all):>5}  {show(a_big):>5}  "
            f"{show(a_pass):>5}")
    say("\n== targets:")
    for t in targets(report, settings):
        say(f"  {t['target']}: {t['measured']} -> {t['verdict']}")


def job_table(summaries: list[JobSummary]) -> list[str]:
    """One Markdown row per job: processes, failures, wall time and its main result."""
    lines = ["| job | processes | failed | wall | result |", "|---|---|---|---|---|"]
    for s in summaries:
        result = s.note if not s.failures else f"FAILED: {s.failures[0]}"
        lines.append(f"| {s.name} | {s.processes} | {len(s.failures)} | {s.seconds:.1f} s | "
                     f"{result.replace('|', '/')} |")
    return lines


def _print_tables(report: dict[str, Any], settings: Settings,
                  summaries: list[JobSummary]) -> None:
    for problem, info in PROBLEMS.items():
        say(f"\n== {info['title']}\n")
        for line in method_table(report.get("rows", []), problem, settings):
            say(line)
    say("\n== jobs\n")
    for line in job_table(summaries):
        say(line)


def run_jobs(ctx: Run) -> list[JobSummary]:
    """Every job of :data:`bench.jobs.JOBS`, in order, timed."""
    summaries = []
    for job in JOBS:
        if ctx.settings.jobs and job.NAME not in ctx.settings.jobs:
            continue
        start = time.perf_counter()
        summary = job.run(ctx)
        summary.seconds = time.perf_counter() - start
        summaries.append(summary)
    return summaries


def main(argv: list[str] | None = None) -> int:
    """Run the benchmarks (or, with ``--child``, one job of a run).

    Returns
    -------
    int
        0, or 1 when a ``--quick`` run had a failed job.
    """
    args = parse_args(argv)
    if args.child:
        return child_main(args.child)
    settings = settings_from(args)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up the data on kill
    clock = Clock(settings.budget)
    given = argv if argv is not None else sys.argv[1:]
    command = "make bench" if not given else "python benchmarks/run.py " + " ".join(given)
    report: dict[str, Any] = {
        "command": command,
        "date": datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "machine": machine(), "load_start": load_average(), "code_start": code_state(),
    }
    say(f"symcal benchmarks: N = {', '.join(fmt_n(n) for n in settings.sizes)}; "
        f"machine: {report['machine']['CPU']}; load {report['load_start']}")
    report["residual_check"] = check_residuals()
    say(f"peer residuals vs symcal: {report['residual_check']}")
    if max(report["residual_check"].values()) > 1e-12:
        raise SystemExit("the numpy residuals of benchmarks/bench/peers.py disagree with "
                         "symcal's")
    with tempfile.TemporaryDirectory(prefix="symcal-bench-") as tmp:
        workdir = Path(tmp)
        # compiled functions (symcal.base.jit) in a cache of this run only: every run builds
        # them once (job startup) and measures the same state, whatever ran before
        os.environ["XDG_CACHE_HOME"] = str(workdir / "cache")
        ctx = Run(settings, workdir, make_data(workdir, settings.sizes), report, clock)
        summaries = run_jobs(ctx)
    report["load_end"] = load_average()
    report["code_end"] = code_state()
    report["elapsed"] = clock.elapsed()
    if report["code_end"]["hash"] != report["code_start"]["hash"]:
        say("WARNING: symcal's source changed during the run; the results mix versions")
    _console_summary(report, settings)
    text = render(report, settings)  # rendered in every run, so --quick checks it too
    if settings.quick:
        _print_tables(report, settings, summaries)
    if settings.out is not None:
        if settings.jobs and settings.out.exists():
            text = splice(settings.out.read_text(encoding="utf-8"), text, report)
        atomic_write(settings.out, text)
        say(f"\nwrote {settings.out} ({report['elapsed'] / 60:.1f} min)")
    else:
        say(f"\nquick run: {report['elapsed']:.1f} s, nothing written")
    if args.json:
        write_json(Path(args.json), report)
    failed = [s.name for s in summaries if s.failures]
    return 1 if settings.quick and failed else 0
