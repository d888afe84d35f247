"""Job ``profile``: where symcal's time per pass goes, on one full chunk and the smallest N.

Only symcal's own objects are timed (``Mapped.chunk`` and ``Objective``'s evaluators), so
the profile follows whatever ``symcal.base.numeric`` does; the cost of building a mapped
function is taken as the first call minus a repeated call.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from ..children import run_child
from ..config import PROBLEMS, ROOT, SEED, Run
from ..fmt import say
from ..measure import best, peak_rss_mib, timed
from ..problems import load_columns, single_stage_problem
from .base import JobSummary, summarise

NAME = "profile"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Profile both problems on ``job["chunk"]`` and ``job["small"]`` data files."""
    out: dict[str, Any] = {}
    for problem in ("linear", "dual"):
        for label in ("chunk", "small"):
            try:
                out[f"{problem}/{label}"] = profile_problem(
                    problem, job[label][problem], job["start"][problem])
            except Exception as exc:  # noqa: BLE001 - a profile must not stop the run
                out[f"{problem}/{label}"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def profile_problem(problem: str, data_path: str, start_path: str) -> dict[str, Any]:
    """Times of one problem's per-chunk evaluation and of each ``Objective`` pass."""
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import needed_columns
    from symcal.solvers.objective import Objective

    prob = single_stage_problem(problem)
    cols = load_columns(data_path)
    n = len(next(iter(cols.values())))
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    theta = np.load(start_path)
    stage = prob.stages[0]
    free = np.array([p.name in stage.free for p in prob.parameters])
    u = data.matrix(prob.columns)

    def fresh() -> Any:
        return Objective(prob, stage.constraints, free)

    objective = fresh()
    rec: dict[str, Any] = {"n": n}
    lin = objective._mapped("linearised", [objective.g, objective.jac.T])
    before = peak_rss_mib()
    rec["chunk_first"] = timed(lambda: lin.chunk(theta, u))
    rec["chunk_first_peak_mib"] = peak_rss_mib() - before
    rec["chunk"] = best(lambda: lin.chunk(theta, u))
    try:  # the mapped function's work vector, if symcal keeps it where it does today
        entry = lin._maps[max(lin._maps)]
        fn = entry[0] if isinstance(entry, tuple) else entry
        rec["work_mib"] = fn.sz_w() * 8 / 2**20
    except Exception:  # noqa: BLE001 - informative only
        rec["work_mib"] = None
    for name in ("normal_equations", "accumulate_r", "cost"):
        evaluate = functools.partial(getattr(fresh(), name), data, theta)
        if name == "accumulate_r":   # a new point every call: an Objective keeps its last R
            evaluate = functools.partial(_moving, fresh().accumulate_r, data, theta,
                                         iter(range(1, 1_000)))
        first = timed(evaluate)
        rec[name] = best(evaluate)
        rec[f"{name}_first"] = first
    return rec


def _moving(method: Any, data: Any, theta: np.ndarray, calls: Any) -> Any:
    """``method(data, θ')`` at a point moved by 1e-12 of θ more at every call."""
    return method(data, theta * (1 + 1e-12 * next(calls)))


def _describe(rec: dict[str, Any]) -> str:
    return ", ".join(f"{m} {v:.3g}" if isinstance(v, float) else f"{m} {v}"
                     for m, v in rec.items())


def run(ctx: Run) -> JobSummary:
    """Simulate one chunk's worth of data per problem and profile it in a child."""
    from symcal.base.numeric import CHUNK
    from symcal.data.dataset import write_table
    from symcal.simulation import load_scenario, simulate_run

    sizes = ctx.settings.sizes
    n_prof = min(max(sizes), CHUNK)
    files: dict[str, dict[str, str]] = {"chunk": {}, "small": {}}
    for problem, info in PROBLEMS.items():
        path = ctx.workdir / f"profile_{problem}.npz"
        write_table(path, simulate_run(load_scenario(ROOT / info["scenario"]), "calibration",
                                       seed=SEED, n=n_prof))
        files["chunk"][problem] = str(path)
        files["small"][problem] = ctx.files[(problem, min(sizes))]["data"]
    starts = {p: ctx.files[(p, min(sizes))]["start"] for p in PROBLEMS}
    profile = run_child({"kind": NAME, **files, "start": starts}, ctx.settings, timeout=600)
    ctx.report["profile"] = profile
    say("== profile: " + "; ".join(f"{k}: {_describe(rec)}" for k, rec in profile.items()
                                   if isinstance(rec, dict)))
    summary = summarise(NAME, [profile], f"chunk of {n_prof} and N = {min(sizes)}")
    summary.failures += [f"{k}: {rec['error']}" for k, rec in profile.items()
                         if isinstance(rec, dict) and "error" in rec]
    return summary
