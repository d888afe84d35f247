"""Job ``improve``: the improvement loop's rounds, timed on the bundled problems.

``symcal.revise.improve.improve`` on each bundled problem with its own simulated data,
in a fresh process each, its progress lines time-stamped: round 0 is the first solve and
diagnosis, round k every candidate tried (each one solve and diagnosis) until one is kept
or none pays, and the last round the one that found nothing more to keep.  A round's
time is from the end of the previous one to its own last line.
"""

from __future__ import annotations

import tempfile
import time
from typing import Any

from ..children import run_child
from ..config import ROOT, Run
from ..fmt import say
from .base import JobSummary, summarise

NAME = "improve"
#: The bundled problems whose loop is timed (each simulates its own data).
PROBLEMS = ("problems/platen_self_calibration.yaml",
            "problems/platen_self_calibration_implicit.yaml",
            "problems/dual_sensor_calibration.yaml",
            "problems/dual_sensor_calibration_implicit.yaml",
            "examples/hidden_effect/problem.yaml",
            "examples/accelerometer_triad/problem_fixed.yaml",
            "examples/diff_drive/problem_fixed.yaml",
            "examples/planar_arm/problem_fixed.yaml")
QUICK = ("problems/platen_self_calibration.yaml",)


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Run the loop on one problem; every progress line with its time."""
    from symcal.revise.improve import improve

    lines: list[tuple[float, str]] = []
    with tempfile.TemporaryDirectory(prefix="symcal-bench-improve-") as out:
        start = time.perf_counter()
        result = improve(ROOT / job["problem"], out, max_rounds=job["max_rounds"],
                         progress=lambda line: lines.append((time.perf_counter() - start,
                                                             line)))
        total = time.perf_counter() - start
    ends: dict[int, float] = {}
    tries: dict[int, int] = {}
    for t, line in lines:
        if line.startswith("round "):
            k = int(line.split()[1].rstrip(":"))
            ends[k] = t
            tries[k] = tries.get(k, 0) + ("trying" in line or "tried" in line)
    last = max(ends, default=0)
    if result.rounds and len(result.rounds) - 1 < last or not result.quiet:
        ends[last] = total                 # the round that kept nothing ends with the loop
    else:
        ends[last + 1] = total             # the final diagnosis after the last kept round
    previous, rounds = 0.0, []
    for k in sorted(ends):
        rounds.append({"round": k, "seconds": ends[k] - previous, "lines": tries.get(k, 0)})
        previous = ends[k]
    return {"total": total, "rounds": rounds, "kept": len(result.rounds) - 1,
            "quiet": result.quiet, "added": [r.added for r in result.rounds[1:]],
            "lines": [f"{t:7.2f} s  {line}" for t, line in lines]}


def run(ctx: Run) -> JobSummary:
    """The loop on every bundled problem, each in a fresh process."""
    problems = QUICK if ctx.settings.quick else PROBLEMS
    results: dict[str, dict[str, Any]] = {}
    for problem in problems:
        job = {"kind": NAME, "problem": problem, "max_rounds": 1 if ctx.settings.quick else 5}
        results[problem] = run_child(job, ctx.settings, timeout=900)
        r = results[problem]
        say(f"== improve {problem}: " + (f"{r['total']:.1f} s, {r['kept']} kept, "
                                         f"rounds {[round(x['seconds'], 1) for x in r['rounds']]}"
                                         if "total" in r else f"ERROR {r['error']}"))
    ctx.report["improve"] = results
    note = ", ".join(f"{p.split('/')[-1]} {r.get('total', float('nan')):.1f} s"
                     for p, r in results.items())
    return summarise(NAME, list(results.values()), note)


def table(report: dict[str, Any]) -> list[str]:
    """The RESULTS.md section of the job (empty when it did not run)."""
    results = report.get("improve")
    if not results:
        return []
    lines = ["", "## The improvement loop, round by round", "",
             "`symcal.revise.improve.improve` (what `symcal improve` runs) on each bundled "
             "problem with its own simulated data, in a fresh process (the problem's build "
             "and data included, `import symcal` not).  Round 0 is the first solve and "
             "diagnosis; each later round tries candidates (one solve and diagnosis each) "
             "until one is kept; the last round is the one that kept nothing, or the final "
             "diagnosis.", "",
             "| problem | total | rounds kept | quiet | time per round (s) | slowest round |",
             "|---|---|---|---|---|---|"]
    for problem, r in results.items():
        if "total" not in r:
            lines.append(f"| `{problem}` | — | — | — | error: {r.get('error')} | — |")
            continue
        per = ", ".join(f"{x['seconds']:.1f}" for x in r["rounds"])
        slowest = max(x["seconds"] for x in r["rounds"])
        lines.append(f"| `{problem}` | {r['total']:.1f} s | {r['kept']} "
                     f"({', '.join(map(str, r['added'])) or 'none'}) | "
                     f"{'yes' if r['quiet'] else 'no'} | {per} | {slowest:.1f} s |")
    return [*lines, ""]
