"""Job ``hugelog``: one log of 1e7 rows kept as Parquet shards, its passes on Dask, and
the 1e8 projection from the measured cost per shard.

The §3.2 dual problem's single-stage objective (all constraints, all 49 parameters, as
in the main tables) on 10 shards of 1e6 rows (each simulated with its own seed, written
with pyarrow).  On an embedded local Dask cluster of 2 worker processes (one thread and
one BLAS thread each), one pass of each kind: ``cost`` (residuals), ``normal_equations``
(the pass of an IPOPT iteration) and ``accumulate_r`` (TSQR: the pass of an ``lm`` step).  Each
worker reads its own shards and returns a small reduction; the lead never holds the log.
Measured: every pass's wall time, the peak RSS of the lead and of each worker.  The 1e8
projection: 100 shards at the measured cost per shard, on the same 2 workers, for one
pass of each kind and for a solve by the default path, ``lm``: 4 TSQR passes (what the
dual solve makes at N = 1e6 from the common start; the IPOPT path makes 7 linearised
passes and 1 TSQR).  ``--quick``: 4 shards of 5000 rows.

The command line on shards: ``symcal solve problems/dual_sensor_calibration.yaml --data
calibration=DIR --quiet`` (the bundled problem as a user runs it: its three stages,
estimated weighting, the simulated fly-by held out, the whole analysis) on folders of
:data:`CLI_SHARDS` shards of :data:`CLI_ROWS` rows, the whole command timed (start-up
included).  Its cost is ``a + b·shards``: the fixed part and the cost per shard, fitted
to the runs, give the 1e8 projection on this path (the command reads the shards in its
own process, one shard per thread and one thread per usable core).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from ..children import run_child
from ..config import PROBLEMS, ROOT, SEED, Run
from ..fmt import fmt_n, say
from ..measure import peak_rss_mib
from .base import JobSummary

NAME = "hugelog"
#: (shards, rows per shard) of a full run and of ``--quick``.
FULL = (10, 1_000_000)
QUICK = (4, 5_000)
WORKERS = 2
#: Passes of the dual solve at N = 1e6 by the default path (lm: 4 TSQR passes), for the
#: 1e8 projection.
SOLVE_PASSES = {"accumulate_r": 4}
KINDS = ("cost", "normal_equations", "accumulate_r")
#: Shard counts and rows per shard of the command-line runs (full run; ``--quick``: 1, 2
#: shards of the quick size).
CLI_SHARDS = (2, 8)
CLI_ROWS = 100_000
CLI_PROBLEM = "problems/dual_sensor_calibration.yaml"


def _worker_peak() -> float:
    """Peak RSS of this process in MiB (runs on a worker)."""
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> None:
    """Reset this process's peak RSS (Linux: ``5`` to ``/proc/self/clear_refs``)."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")
    except OSError:  # pragma: no cover - not Linux, or not allowed: the peak stays
        pass


def cli_child(job: dict[str, Any]) -> dict[str, Any]:
    """Time ``symcal solve PROBLEM --data calibration=DIR`` on folders of shards."""
    import subprocess
    import sys

    import pyarrow as pa
    import pyarrow.parquet as pq

    from symcal.simulation import load_scenario, simulate_run

    scenario = load_scenario(ROOT / PROBLEMS["dual"]["scenario"])
    runs = []
    with tempfile.TemporaryDirectory(prefix="symcal-hugecli-", dir=job["workdir"]) as tmp:
        for count in job["shards"]:
            folder = Path(tmp) / f"log-{count}"
            folder.mkdir()
            for i in range(count):
                cols = simulate_run(scenario, "calibration", seed=SEED + i, n=job["rows"])
                pq.write_table(pa.table(cols), folder / f"part-{i:04d}.parquet")
            start = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "symcal", "solve", CLI_PROBLEM,
                                   "--data", f"calibration={folder}", "--quiet"],
                                  capture_output=True, text=True, cwd=ROOT)
            seconds = time.perf_counter() - start
            runs.append({"shards": count, "rows": count * job["rows"], "seconds": seconds,
                         "exit": proc.returncode, "stderr": proc.stderr[-400:]})
    return {"runs": runs, "rows_per_shard": job["rows"]}


def cli_projection(cli: dict[str, Any], n: int = 100_000_000) -> dict[str, float]:
    """``a + b·shards`` fitted to the command's runs (least squares), and its value at
    ``n`` rows in shards of the same size."""
    import numpy as np

    shards = np.array([r["shards"] for r in cli["runs"]], dtype=float)
    seconds = np.array([r["seconds"] for r in cli["runs"]])
    b, a = np.polyfit(shards, seconds, 1)
    count = n / cli["rows_per_shard"]
    return {"fixed": float(a), "per_shard": float(b), "shards": count,
            "seconds": float(a + b * count)}


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Write the shards, then time one pass of each kind on a local Dask cluster."""
    if job.get("cli"):
        return cli_child(job)
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from symcal.data.loading import needed_columns
    from symcal.data.shards import open_shards
    from symcal.simulation import load_scenario, simulate_run
    from symcal.solvers.dask_executor import dask_executor
    from symcal.solvers.objective import Objective

    from ..problems import single_stage_problem

    shards, rows = job["shards"], job["rows"]
    problem = single_stage_problem("dual")
    scenario = load_scenario(ROOT / PROBLEMS["dual"]["scenario"])
    out: dict[str, Any] = {"shards": shards, "rows_per_shard": rows, "workers": WORKERS}
    with tempfile.TemporaryDirectory(prefix="symcal-hugelog-", dir=job["workdir"]) as tmp:
        folder = Path(tmp)
        start = time.perf_counter()
        for i in range(shards):
            cols = simulate_run(scenario, "calibration", seed=SEED + i, n=rows)
            pq.write_table(pa.table(cols), folder / f"part-{i:04d}.parquet")
            del cols
        out["write_seconds"] = time.perf_counter() - start
        out["bytes"] = sum(p.stat().st_size for p in folder.glob("*.parquet"))
        out["write_peak_mib"] = peak_rss_mib()
        _reset_peak()                   # from here on: the lead's peak during the passes
        start = time.perf_counter()
        log = open_shards("calibration", folder, needed_columns(problem))
        out["open_seconds"] = time.perf_counter() - start
        out["n"] = log.n
        stage = problem.stages[0]
        free = np.array([p.name in stage.free for p in problem.parameters])
        theta = np.array([p.value for p in problem.parameters])
        start = time.perf_counter()
        with dask_executor(workers=WORKERS) as executor:
            out["cluster_seconds"] = time.perf_counter() - start
            objective = Objective(problem, stage.constraints, free, executor=executor)
            objective.cost(log, theta)      # workers import symcal, load the functions
            passes: dict[str, float] = {}
            for kind in KINDS:
                start = time.perf_counter()
                getattr(objective, kind)(log, theta)
                passes[kind] = time.perf_counter() - start
            out["passes"] = passes
            out["worker_peak_mib"] = sorted(executor.client.run(_worker_peak).values())
        out["lead_peak_mib"] = peak_rss_mib()
    return out


def projection(result: dict[str, Any], n: int = 100_000_000) -> dict[str, float]:
    """Seconds at ``n`` rows (same shard size, same workers) from the measured passes."""
    scale = n / result["n"]
    out = {kind: t * scale for kind, t in result["passes"].items()}
    out["solve"] = sum(out[k] * c for k, c in SOLVE_PASSES.items())
    return out


def run(ctx: Run) -> JobSummary:
    """One child: shards written, passes timed, the 1e8 projection computed."""
    shards, rows = QUICK if ctx.settings.quick else FULL
    result = run_child({"kind": NAME, "shards": shards, "rows": rows,
                        "workdir": str(ctx.workdir)}, ctx.settings, timeout=1800)
    ctx.report["hugelog"] = result
    if "error" in result:
        return JobSummary(NAME, 1, [str(result["error"])], "failed")
    result["projection"] = projection(result)
    cli = run_child({"kind": NAME, "cli": True, "workdir": str(ctx.workdir),
                     "shards": (1, 2) if ctx.settings.quick else CLI_SHARDS,
                     "rows": QUICK[1] if ctx.settings.quick else CLI_ROWS},
                    ctx.settings, timeout=3600)
    failures = []
    if "error" in cli:
        failures.append(f"command line on shards: {cli['error']}")
    else:
        failures += [f"symcal solve on {r['shards']} shards exited {r['exit']}: {r['stderr']}"
                     for r in cli["runs"] if r["exit"] != 0]
        if not failures:
            cli["projection"] = cli_projection(cli)
    result["cli"] = cli
    p = result["passes"]
    note = (f"{fmt_n(result['n'])} rows in {shards} Parquet shards on {WORKERS} Dask "
            f"workers: cost {p['cost']:.1f} s, normal equations {p['normal_equations']:.1f} s,"
            f" TSQR {p['accumulate_r']:.1f} s per pass; workers' peak "
            f"{max(result['worker_peak_mib']):.0f} MiB; 1e8 solve projected "
            f"{result['projection']['solve'] / 60:.1f} min")
    if "projection" in cli:
        note += (f"; symcal solve on shards: 1e8 rows projected "
                 f"{cli['projection']['seconds'] / 3600:.1f} h")
    say("== " + note)
    return JobSummary(NAME, 2, failures, note)


def table(report: dict[str, Any]) -> list[str]:
    """The RESULTS.md section of the job (empty when it did not run)."""
    r = report.get("hugelog")
    if not r or "error" in r or "projection" not in r:
        return []
    p, proj = r["passes"], r["projection"]
    lines = [
        "", f"## One huge log on Dask: {fmt_n(r['n'])} rows", "",
        f"The §3.2 dual objective (single stage, 49 parameters) on {r['shards']} Parquet "
        f"shards of {fmt_n(r['rows_per_shard'])} rows ({r['bytes'] / 2**20:.0f} MiB on "
        f"disk; simulated and written in {r['write_seconds']:.1f} s, opened from the "
        f"metadata in {r['open_seconds'] * 1e3:.0f} ms), on an embedded local Dask "
        f"cluster of {r['workers']} worker processes (started in "
        f"{r['cluster_seconds']:.1f} s).  Each task reads one shard and returns a small "
        "reduction; the lead reduces them in shard order.", "",
        "| pass | measured | per shard (× workers) | projected at N = 1e8 |",
        "|---|---|---|---|",
    ]
    for kind in KINDS:
        per_shard = p[kind] * r["workers"] / r["shards"]
        lines.append(f"| `{kind}` | {p[kind]:.2f} s | {per_shard:.2f} s | "
                     f"{proj[kind]:.0f} s |")
    lines += [
        "| dual solve by the default path, `lm` (4 × `accumulate_r`) | — | — | "
        f"{proj['solve']:.0f} s ({proj['solve'] / 60:.1f} min) |", "",
        f"Peak RSS during the passes: lead {r['lead_peak_mib']:.0f} MiB (it simulated and "
        f"wrote the shards first, at a peak of {r['write_peak_mib']:.0f} MiB; the peak was "
        "reset before opening the log), workers "
        f"{', '.join(f'{m:.0f}' for m in r['worker_peak_mib'])} MiB: bounded by one shard, "
        "whatever the length of the log (a 1e8-row log is 100 such shards; the projection "
        "assumes the same cost per shard and the same 2 workers, and needs no more memory).",
    ]
    return lines + _cli_table(r.get("cli", {}))


def _cli_table(cli: dict[str, Any]) -> list[str]:
    """The command line on shards: its runs and the 1e8 projection."""
    if "projection" not in cli:
        return []
    proj = cli["projection"]
    lines = ["", "### The command line on a log kept as shards", "",
             f"`symcal solve {CLI_PROBLEM} --data calibration=DIR --quiet`, the whole "
             "command (start-up, the problem's build, its simulated fly-by, three stages "
             "with estimated weighting, the analysis), DIR holding Parquet shards of "
             f"{fmt_n(cli['rows_per_shard'])} rows each.  The command reads the shards in "
             "its own process, one shard per thread and one thread per usable core (a "
             "shard's own passes run in its thread).", "",
             "| shards | rows | time |", "|---|---|---|"]
    lines += [f"| {r['shards']} | {fmt_n(r['rows'])} | {r['seconds']:.1f} s |"
              for r in cli["runs"]]
    lines += ["", f"Fitted `a + b·shards`: fixed {proj['fixed']:.1f} s, "
              f"{proj['per_shard']:.2f} s per shard of {fmt_n(cli['rows_per_shard'])} rows, "
              f"so 1e8 rows ({proj['shards']:.0f} shards) take "
              f"{proj['seconds']:.0f} s ({proj['seconds'] / 3600:.1f} h) on this path."]
    return lines
