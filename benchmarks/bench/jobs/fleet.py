"""Job ``fleet``: a fleet of units on Dask (1 and 2 local workers) against a plain loop of
``symcal.solve`` over the same units.

Full run: 200 units × 1e4 observations of the §3.1 linear problem (each unit its own
simulated calibration run and fly-by, seed = unit number), in NPZ files.  ``--quick``:
4 units × the run's smallest N.  Each of the three ways runs in a fresh process, so
every one pays its own start: the loop its imports and one problem build, the fleet its
imports, the local cluster's start (worker processes that import symcal and build the
problem once each) and its shut-down.  The loop's estimates are saved and every fleet
run is checked against them (max |Δθ|, which must be at most 1e-12).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from ..children import run_child
from ..config import PROBLEMS, ROOT, Run
from ..fmt import fmt_n, say
from ..measure import peak_rss_mib
from .base import JobSummary

NAME = "fleet"
#: (units, observations per unit) of a full run.
FULL = (200, 10_000)
QUICK_UNITS = 4
WORKERS = (1, 2)


def shape(ctx: Run) -> tuple[int, int]:
    """(units, observations per unit) of this run."""
    return (QUICK_UNITS, min(ctx.settings.sizes)) if ctx.settings.quick else FULL


def make_fleet(folder: Path, units: int, n: int) -> Path:
    """Simulate ``units`` units' calibration runs (N = ``n``) and fly-bys into ``folder``."""
    from symcal.data.dataset import write_table
    from symcal.simulation import load_scenario, simulate_run

    scenario = load_scenario(ROOT / PROBLEMS["linear"]["scenario"])
    for i in range(units):
        unit = folder / f"unit-{i:04d}"
        unit.mkdir(parents=True)
        write_table(unit / "calibration.npz", simulate_run(scenario, "calibration", seed=i,
                                                           n=n))
        write_table(unit / "flyby.npz", simulate_run(scenario, "flyby", seed=i))
    return folder


def child(job: dict[str, Any]) -> dict[str, Any]:
    """``job["how"]`` is ``"loop"`` (``symcal.solve`` unit by unit, estimates saved to
    ``job["estimates"]``) or ``"fleet"`` (``symcal.solve_fleet`` with ``job["workers"]``
    local workers, compared with the saved estimates)."""
    start = time.perf_counter()
    import symcal

    imported = time.perf_counter() - start
    t0 = time.perf_counter()  # the problem's build counts, as the workers' builds do
    problem = symcal.load_problem(ROOT / PROBLEMS["linear"]["path"])
    folder = Path(job["fleet"])
    units = sorted(p for p in folder.iterdir() if p.is_dir())
    if job["how"] == "warm":     # the problem's compiled twins into the run's cache
        import os

        os.environ["SYMCAL_JIT"] = "on"
        unit = units[0]
        symcal.solve(problem, {p.stem: str(p) for p in unit.iterdir()})
        return {"seconds": time.perf_counter() - t0}
    if job["how"] == "loop":
        estimates, failed = {}, 0
        for unit in units:
            files = {p.stem: str(p) for p in unit.iterdir()}
            result = symcal.solve(problem, files)
            estimates[unit.name] = {n: p.value for n, p in result.params.items()}
            failed += not result.success
        seconds = time.perf_counter() - t0
        Path(job["estimates"]).write_text(json.dumps(estimates))
        return {"seconds": seconds, "import": imported, "units": len(units),
                "failed": failed, "peak_mib": peak_rss_mib()}
    fleet = symcal.solve_fleet(problem, folder, workers=job["workers"])
    seconds = time.perf_counter() - t0
    reference = json.loads(Path(job["estimates"]).read_text())
    worst = 0.0
    for name, res in fleet.results.items():
        got = {n: p.value for n, p in res.params.items()}
        worst = max(worst, max(abs(got[k] - v) for k, v in reference[name].items()))
    return {"seconds": seconds, "import": imported, "units": len(fleet.units),
            "failed": len(fleet.failed), "max_diff": worst, "peak_mib": peak_rss_mib()}


def run(ctx: Run) -> JobSummary:
    """Make the fleet, then time the loop and the fleet with 1 and 2 workers."""
    units, n = shape(ctx)
    folder = make_fleet(ctx.workdir / "fleet", units, n)
    estimates = ctx.workdir / "fleet-estimates.json"
    base = {"kind": NAME, "fleet": str(folder), "estimates": str(estimates)}
    # warm, as every solve after the first of a problem on a machine: the bundled
    # problem's compiled twins in the run's cache before the loop and the fleets
    run_child({**base, "how": "warm"}, ctx.settings, timeout=1800)
    results: dict[str, dict[str, Any]] = {
        "loop": run_child({**base, "how": "loop"}, ctx.settings, timeout=1800)}
    for w in WORKERS:
        if "error" in results["loop"]:
            break
        results[f"{w} worker(s)"] = run_child({**base, "how": "fleet", "workers": w},
                                              ctx.settings, timeout=1800)
    ctx.report["fleet"] = {"units": units, "n": n, "runs": results}
    failures = [f"{k}: {r['error']}" for k, r in results.items() if "error" in r]
    failures += [f"{k}: {r['failed']} unit(s) failed" for k, r in results.items()
                 if r.get("failed")]
    failures += [f"{k}: estimates differ from the loop's by {r['max_diff']:.1e}"
                 for k, r in results.items() if r.get("max_diff", 0.0) > 1e-12]
    loop = results["loop"].get("seconds")
    parts = [f"{k} {r['seconds']:.2f} s" + (f" ({loop / r['seconds']:.2f}× the loop)"
                                            if loop and k != "loop" else "")
             for k, r in results.items() if "seconds" in r]
    note = f"fleet of {units} units × N={fmt_n(n)}: " + ", ".join(parts)
    say("== " + note)
    return JobSummary(NAME, len(results), failures, note)


def table(report: dict[str, Any]) -> list[str]:
    """The fleet section of RESULTS.md."""
    fleet = report.get("fleet")
    if not fleet:
        return []
    runs = fleet["runs"]
    loop = runs.get("loop", {}).get("seconds")
    lines = ["", f"## A fleet: {fleet['units']} units × N = {fmt_n(fleet['n'])} "
                 "(§3.1 linear problem)", "",
             "Each unit has its own simulated calibration run and fly-by (NPZ).  *loop* is "
             "`symcal.solve` unit by unit in one process; the fleet rows are "
             "`symcal.solve_fleet` on an embedded Dask `LocalCluster` (worker processes, "
             "forked from the client on Linux, one thread each, symcal's passes on one BLAS "
             "thread), the "
             "cluster's start, the workers' "
             "imports and problem builds, and its shut-down included.  Each in a fresh "
             "process; the time includes the problem's build and excludes only "
             "`import symcal`.  The problem's compiled twins are in the run's cache "
             "beforehand (one solve with `SYMCAL_JIT=on`), for the loop and the fleets "
             "alike.  Max |Δθ| is against the "
             "loop's estimates (required ≤ 1e-12).", "",
             "| how | time | speed-up over the loop | units failed | max \\|Δθ\\| | "
             "peak RSS (client) |",
             "|---|---|---|---|---|---|"]
    for how, r in runs.items():
        if "seconds" not in r:
            lines.append(f"| {how} | — | — | — | — | error: {r.get('error')} |")
            continue
        speed = "1" if how == "loop" or not loop else f"{loop / r['seconds']:.2f}×"
        diff = "—" if "max_diff" not in r else f"{r['max_diff']:.1e}"
        lines.append(f"| {how} | {r['seconds']:.2f} s | {speed} | {r['failed']} | {diff} | "
                     f"{r['peak_mib']:.0f} MiB |")
    return lines
