"""Job ``solve``: every (problem, N, method) timed in its own process: the main tables."""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

from ..children import run_child
from ..config import PROBLEMS, UNCAPPED, Run, Settings
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
    out: Outcome | None = None
    while len(times) < job["repeats"]:
        start = time.perf_counter()
        out = run(theta0.copy())
        times.append(time.perf_counter() - start)
        if sum(times) + times[-1] > job["repeat_budget"]:
            break
    assert out is not None
    return {
        "times": times, "seconds": statistics.median(times), "iterations": out.iterations,
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


def skip_reason(name: str, guess: float | None, settings: Settings,
                clock: Clock) -> str | None:
    """Why a capped method is not started at the next size, if it is not."""
    if name in UNCAPPED or guess is None:
        return None
    if guess > settings.cap:
        return f"projected {guess:.0f} s > the {settings.cap:.0f} s cap"
    if guess > clock.left():
        return (f"projected {guess:.0f} s would pass the run's "
                f"{settings.budget / 60:.0f} min budget")
    return None


def _line(row: dict[str, Any]) -> str:
    iters = "—" if row["iterations"] is None else row["iterations"]
    return (f"{row['seconds']:9.3f} s (median of {len(row['times'])})  "
            f"peak {row['peak_mib']:6.0f} MiB  iter {iters!s:>4}  "
            f"passes {row['evaluations']!s:>5}  J = {row['cost']:.12e}"
            f"{'  STOPPED AT CAP' if row['stopped'] else ''}")


def run(ctx: Run) -> JobSummary:
    """Every (problem, N, method), N ascending; symcal and the floor first at each N."""
    settings, clock = ctx.settings, ctx.clock
    rows: list[dict[str, Any]] = []
    ctx.report["rows"] = rows
    history: dict[tuple[str, str], list[tuple[int, float]]] = {}
    dead: dict[tuple[str, str], str] = {}
    results = []
    for n in settings.sizes:
        for problem, info in PROBLEMS.items():
            for name in info["methods"]:
                key = (problem, name)
                row: dict[str, Any] = {"problem": problem, "n": n, "method": name}
                rows.append(row)
                guess = projected(history.get(key, []), n)
                why = dead.get(key) or skip_reason(name, guess, settings, clock)
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
                if result["stopped"]:
                    dead[key] = f"stopped at its cap at N = {fmt_n(n)}"
                say(f"  {problem:6s} N={n:>8} {name:16s} {_line(result)}")
    skipped = sum("skipped" in r for r in rows)
    return summarise(NAME, results, f"{len(rows)} rows, {len(results)} timed, "
                                    f"{skipped} skipped")
