"""Job ``solve``: every (problem, N, method) timed in its own process: the main tables.

Each process calls the method once more than ``repeats``: the first call is its *cold*
time (a fresh process: CasADi's mapped functions and buffers built, a peer's XLA
program compiled), the median of the others its *warm* time, the one compared.  symcal's
rows run in the run's compile cache, where the compiled twins are (job ``startup``), as
every solve after the first of a problem on a machine does; their cold time comes from
one more process with an empty compile cache.
"""

from __future__ import annotations

import importlib.util
import statistics
import tempfile
import time
from typing import Any

import numpy as np

from ..children import run_child
from ..config import (
    EXACT_PEERS,
    MEMORY_CAP_MIB,
    PROBLEMS,
    SYMCAL_ROWS,
    UNCAPPED,
    Run,
    Settings,
)
from ..fmt import fmt_n, say
from ..measure import Clock, peak_rss_mib, rss_now_mib
from ..methods import Outcome, method
from ..problems import cost, load_columns
from .base import JobSummary, summarise

NAME = "solve"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Time one method on one dataset, ``repeats`` times at most (see ``repeat_budget``)."""
    problem = job["problem"]
    cols = load_columns(job["data"])
    theta0 = np.load(job["start"])
    run = method(problem, job["method"], cols, job["cap"])
    baseline = rss_now_mib()
    times: list[float] = []
    cpu: list[float] = []       # CPU seconds of the process (all its threads)
    out: Outcome | None = None
    while len(times) < 1 + job["repeats"]:
        start, start_cpu = time.perf_counter(), time.process_time()
        out = run(theta0.copy())
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        if sum(times) + times[-1] > job["repeat_budget"] and len(times) > 1:
            break
        if len(times) == 1 and times[0] > job["repeat_budget"]:
            break                       # too slow for a warm call: cold only
    assert out is not None
    warm = times[1:] or times
    return {
        "times": warm, "first": times[0], "seconds": statistics.median(warm),
        "cpu_seconds": statistics.median(cpu[1:] or cpu),
        "iterations": out.iterations,
        "evaluations": out.evaluations, "message": out.message,
        "cost": cost(problem, out.theta, cols), "baseline_mib": baseline,
        "peak_mib": peak_rss_mib(), "theta": [float(v) for v in out.theta],
        "stopped": "cap" in out.message, "decrements": out.decrements,
        "passes_by": out.passes_by,
    }


def solve_job(ctx: Run, problem: str, name: str, n: int, cap: float,
              repeats: int | None = None, repeat_budget: float | None = None) -> dict[str, Any]:
    """The child job timing method ``name`` on ``problem`` at N = ``n``."""
    files = ctx.files[(problem, n)]
    settings = ctx.settings
    if repeats is None:
        repeats = settings.repeats if n < 1_000_000 else 1
    return {"kind": NAME, "problem": problem, "method": name, "data": files["data"],
            "start": files["start"], "repeats": repeats,
            "repeat_budget": settings.repeat_budget if repeat_budget is None else repeat_budget,
            "cap": cap}


def projected(history: list[tuple[int, float]], n: int) -> float | None:
    """Time at ``n`` extrapolated linearly from the largest N measured so far."""
    if not history:
        return None
    n1, t1 = history[-1]
    return t1 * n / n1


def not_installed(name: str) -> str | None:
    """Why an exact-Jacobian peer cannot run here (its package is not installed)."""
    if name not in EXACT_PEERS:
        return None
    from ..exact import PEERS

    package = PEERS[name][0]
    needed = {package, "jax"} if package in ("jax", "optimistix") else {package}
    missing = sorted(p for p in needed if importlib.util.find_spec(p) is None)
    if missing:
        return (f"not installed ({', '.join(missing)}): pip install -e \".[bench]\"")
    return None


def skip_reason(name: str, guess: float | None, settings: Settings,
                clock: Clock, memory: float | None = None) -> str | None:
    """Why a capped method is not started at the next size, if it is not."""
    missing = not_installed(name)
    if missing:
        return missing
    if name in UNCAPPED:
        return None
    if memory is not None and memory > MEMORY_CAP_MIB:
        return (f"projected peak memory {memory / 1024:.1f} GiB > the "
                f"{MEMORY_CAP_MIB / 1024:.0f} GiB cap (shared machine)")
    if guess is None:
        return None
    if guess > settings.cap:
        return f"projected {guess:.0f} s > the {settings.cap:.0f} s cap"
    if guess > clock.left():
        return (f"projected {guess:.0f} s would pass the run's "
                f"{settings.budget / 60:.0f} min budget")
    return None


def _line(row: dict[str, Any]) -> str:
    iters = "—" if row["iterations"] is None else row["iterations"]
    return (f"{row['seconds']:9.3f} s (median of {len(row['times'])}; cold "
            f"{row.get('cold', row['first']):.3f} s)  "
            f"peak {row['peak_mib']:6.0f} MiB  iter {iters!s:>4}  "
            f"passes {row['evaluations']!s:>5}  J = {row['cost']:.12e}"
            f"{'  STOPPED AT CAP' if row['stopped'] else ''}")


def run(ctx: Run) -> JobSummary:
    """Every (problem, N, method), N ascending; symcal and the floor first at each N."""
    settings, clock = ctx.settings, ctx.clock
    rows: list[dict[str, Any]] = []
    ctx.report["rows"] = rows
    history: dict[tuple[str, str], list[tuple[int, float]]] = {}
    memories: dict[tuple[str, str], list[tuple[int, float]]] = {}
    # what a first call costs above a warm one (a JAX program's compile): paid once at
    # every N, not in proportion to it
    overhead: dict[tuple[str, str], float] = {}
    dead: dict[tuple[str, str], str] = {}
    results = []
    for n in settings.sizes:
        for problem, info in PROBLEMS.items():
            for name in info["methods"]:
                if settings.methods and name not in settings.methods:
                    continue
                key = (problem, name)
                row: dict[str, Any] = {"problem": problem, "n": n, "method": name}
                rows.append(row)
                guess = projected(history.get(key, []), n)
                if guess is not None:
                    guess += overhead.get(key, 0.0)
                memory = projected(memories.get(key, []), n)
                why = dead.get(key) or skip_reason(name, guess, settings, clock, memory)
                if why:
                    row["skipped"] = why
                    say(f"  {problem:6s} N={n:>8} {name:16s} skipped: {why}")
                    continue
                stop = (settings.cap if name in UNCAPPED
                        else max(1.0, min(settings.cap, clock.left())))
                limit = (max(5 * (guess or 0), 900) if name in UNCAPPED
                         else max(3 * (guess or 0), 3 * stop) + 120)
                result = run_child(solve_job(ctx, problem, name, n, stop), settings,
                                   timeout=limit)
                results.append(result)
                row.update(result)
                if "error" in result:
                    dead[key] = f"failed at N = {fmt_n(n)}: {result['error']}"
                    say(f"  {problem:6s} N={n:>8} {name:16s} ERROR {result['error']}")
                    continue
                history.setdefault(key, []).append((n, result["seconds"]))
                overhead[key] = max(result["first"] - result["seconds"], 0.0)
                memories.setdefault(key, []).append((n, result["peak_mib"]))
                row["cold"] = result["first"]
                if name in SYMCAL_ROWS:
                    with tempfile.TemporaryDirectory(prefix="symcal-cold-") as empty:
                        job = solve_job(ctx, problem, name, n, stop, repeats=0)
                        cold = run_child(job, settings, timeout=limit,
                                         extra_env={"XDG_CACHE_HOME": empty})
                    results.append(cold)
                    if "first" in cold:
                        row["cold"] = cold["first"]
                        row["cold_peak_mib"] = cold["peak_mib"]
                if result["stopped"]:
                    dead[key] = f"stopped at its cap at N = {fmt_n(n)}"
                say(f"  {problem:6s} N={n:>8} {name:16s} {_line(result)}")
    skipped = sum("skipped" in r for r in rows)
    return summarise(NAME, results, f"{len(rows)} rows, {len(results)} timed, "
                                    f"{skipped} skipped")
