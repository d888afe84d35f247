"""Job ``starts``: the common start of every (problem, N), computed once in a child."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..children import run_child
from ..config import PROBLEMS, ROOT, Run
from ..fmt import fmt_n, say
from ..measure import peak_rss_mib
from ..problems import cost, load_columns
from .base import JobSummary, summarise

NAME = "starts"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """The common start: the problem's initial values (linear), or symcal's first two
    stages, in closed form with equal weights (dual).  Saved to ``job["out"]``."""
    import symcal
    from symcal.calibrate.solve import run_stage
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import needed_columns

    prob = symcal.load_problem(ROOT / PROBLEMS[job["problem"]]["path"]).with_weighting("equal")
    theta = np.array([p.value for p in prob.parameters])
    cols = load_columns(job["data"])
    start = time.perf_counter()
    methods = []
    if job["problem"] == "dual":
        data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
        for stage in prob.stages[:2]:
            theta, result = run_stage(prob, stage, data, theta)
            methods.append(result.method)
    seconds = time.perf_counter() - start
    np.save(job["out"], theta)
    return {"seconds": seconds, "methods": methods, "cost": cost(job["problem"], theta, cols),
            "peak_mib": peak_rss_mib()}


def run(ctx: Run) -> JobSummary:
    """Compute every start; stop the run if one fails (every method needs it)."""
    starts: dict[tuple[str, int], dict[str, Any]] = {}
    ctx.report["starts"] = starts
    for problem in PROBLEMS:
        for n in ctx.settings.sizes:
            files = ctx.files[(problem, n)]
            job = {"kind": NAME, "problem": problem, "data": files["data"],
                   "out": files["start"]}
            result = run_child(job, ctx.settings, timeout=1800)
            if "error" in result:
                raise SystemExit(f"could not compute the start for {problem} N={n}: "
                                 f"{result['error']}")
            starts[(problem, n)] = result
    note = ", ".join(f"{p} N={fmt_n(n)} {r['seconds']:.2f} s" for (p, n), r in starts.items())
    say("== common starts: " + note)
    return summarise(NAME, list(starts.values()), note)
