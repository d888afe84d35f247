"""Acceptance of issue 23: symcal's loop on effects and systems it was not tuned on.

Runs the cases of ``tests/acceptance/cases.yaml`` through symcal's command line, as a
user would (simulate, solve, diagnose and the suggestion it prints, improve and its final
problem), for several seeds each, and prints a Markdown table (or writes it with
``--out``, the raw records beside it as JSON)::

    .venv/bin/python benchmarks/acceptance.py                       # every case
    .venv/bin/python benchmarks/acceptance.py --seeds 1 --clean-seeds 5 --cases 'platen_*'
    .venv/bin/python benchmarks/acceptance.py --out build/acceptance.md --jobs 2
    .venv/bin/python benchmarks/acceptance.py --list

Every case gets ``--seeds`` full seeds; clean cases get ``--clean-seeds`` seeds of
diagnose (the false-alarm rates) and ``--clean-improve-seeds`` of improve.  Exit code 0
when the run completed (whatever it measured), 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from acceptance import harness  # noqa: E402  (tests/ is not installed)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line."""
    p = argparse.ArgumentParser(prog="benchmarks/acceptance.py", description=__doc__.split(
        "\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=3, help="full seeds per case (default 3)")
    p.add_argument("--clean-seeds", type=int, default=100,
                   help="diagnose seeds per clean case, for false alarms (default 100)")
    p.add_argument("--clean-seeds-for", action="append", default=[], metavar="GLOB=N",
                   help="diagnose seeds for the clean cases matching GLOB (repeatable)")
    p.add_argument("--clean-improve-seeds", type=int, default=20,
                   help="improve seeds per clean case (default 20)")
    p.add_argument("--seed0", type=int, default=1000, help="first seed (default 1000)")
    p.add_argument("--cases", nargs="+", metavar="CASE",
                   help="case names or globs (default: every case)")
    p.add_argument("--out", type=Path, help="write the Markdown here (and FILE.json)")
    p.add_argument("--jobs", type=int, default=1, help="seeds run at once (default 1)")
    p.add_argument("--work", type=Path, default=Path("/tmp/symcal-acceptance"),
                   help="workspaces (default /tmp/symcal-acceptance)")
    p.add_argument("--keep", action="store_true", help="keep every seed's workspace")
    p.add_argument("--timeout", type=float, default=1800.0,
                   help="seconds one symcal command may take (default 1800)")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--from-json", type=Path, metavar="FILE",
                   help="tabulate a saved run (FILE.json, or the FILE.jsonl a run appends to "
                        "while it runs) instead of running")
    return p.parse_args(argv)


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "log", "-1", "--format=%h %cs %s"],
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "symcal"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return out + (" (symcal/ modified)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    """Run the acceptance cases; print or write the report."""
    args = parse_args(argv)
    try:
        cases = harness.select(harness.load_cases(), args.cases)
    except ValueError as exc:
        print(f"acceptance: error: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for case in cases:
            print(f"{case.name:34} {case.expect:9} {case.kind:13} {case.doc}")
        return 0
    try:
        per = {g: int(n) for g, n in (item.rsplit("=", 1) for item in args.clean_seeds_for)}
    except ValueError:
        print("acceptance: error: --clean-seeds-for takes GLOB=N", file=sys.stderr)
        return 2
    if args.from_json:
        return _tabulate(args, cases)
    settings = harness.Settings(seeds=args.seeds, clean_seeds=args.clean_seeds,
                                clean_seeds_for=per,
                                clean_improve_seeds=args.clean_improve_seeds,
                                seed0=args.seed0, jobs=args.jobs, work=args.work,
                                keep=args.keep, timeout=args.timeout)
    start = time.perf_counter()
    sink = None
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        stream = args.out.with_suffix(".jsonl")
        stream.write_text("", encoding="utf-8")

        def sink(rec: dict) -> None:
            with stream.open("a", encoding="utf-8") as f:
                f.write(json.dumps(rec, default=str) + "\n")

    records = harness.run(cases, settings, progress=lambda s: print(s, file=sys.stderr,
                                                                    flush=True), sink=sink)
    minutes = (time.perf_counter() - start) / 60
    header = "\n".join([
        "# symcal acceptance (issue 23)", "",
        f"Run {datetime.datetime.now().isoformat(timespec='minutes')} on {_commit()}; "
        f"{len(cases)} cases, {len(records)} seed runs, {minutes:.0f} min of wall time with "
        f"{settings.jobs} job(s) on {platform.node()} ({platform.machine()}).",
        "Command: `python benchmarks/acceptance.py " + " ".join(argv or sys.argv[1:]) + "`",
        ""])
    text = harness.markdown(cases, records, settings, header)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
        saved = {"settings": {"seeds": settings.seeds, "seed0": settings.seed0,
                              "clean_seeds": settings.clean_seeds,
                              "clean_improve_seeds": settings.clean_improve_seeds,
                              "commit": _commit()},
                 "records": records}
        args.out.with_suffix(".json").write_text(json.dumps(saved, indent=1, default=str),
                                                 encoding="utf-8")
        print(f"wrote {args.out} and {args.out.with_suffix('.json')}", file=sys.stderr)
    else:
        print(text)
    return 0


def _tabulate(args: argparse.Namespace, cases: list[harness.Case]) -> int:
    """The tables of a saved run (only its cases that are selected)."""
    try:
        given, records = harness.load_records(args.from_json)
    except (OSError, ValueError, KeyError) as exc:
        print(f"acceptance: error: {args.from_json}: {exc}", file=sys.stderr)
        return 2
    names = {c.name for c in cases}
    records = [r for r in records if r["case"] in names]
    present = {r["case"] for r in records}
    chosen = [c for c in cases if c.name in present]
    settings = harness.settings_of(records, given)
    header = "\n".join(["# symcal acceptance (issue 23)", "",
                        f"Tabulated from {args.from_json} (run on "
                        f"{given.get('commit', 'an unrecorded commit')}); {len(chosen)} "
                        f"cases, {len(records)} seed runs.", ""])
    text = harness.markdown(chosen, records, settings, header)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
