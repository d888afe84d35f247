"""Job ``assemble``: YAML to a ready solver, at every N, each in a fresh process."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..children import run_child
from ..config import PROBLEMS, ROOT, Run
from ..fmt import fmt_n, say
from .base import JobSummary, summarise

NAME = "assemble"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Load and build the problem, make each stage's objective and its mapped
    per-observation functions, and evaluate each once on every chunk length N needs
    (which builds whatever ``symcal.base.numeric`` builds on first use)."""
    start = time.perf_counter()
    import symcal
    from symcal.base.numeric import CHUNK, chunks
    from symcal.solvers.objective import Objective

    imported = time.perf_counter()
    prob = symcal.load_problem(ROOT / PROBLEMS[job["problem"]]["path"])
    loaded = time.perf_counter()
    lengths = sorted({s.stop - s.start for s in chunks(job["n"], CHUNK)})
    dummy = np.zeros((len(prob.columns), max(lengths)))
    for stage in prob.stages:
        free = np.array([p.name in stage.free for p in prob.parameters])
        objective = Objective(prob, stage.constraints, free)
        objective.nonlinear()
        theta = np.array([p.value for p in prob.parameters])
        for name, outputs in (("linearised", [objective.g, objective.jac.T]),
                              ("residual", [objective.g])):
            fn = objective._mapped(name, outputs)  # what the solvers build on first use
            for n in lengths:  # one evaluation per chunk length builds what it needs
                fn.chunk(theta, dummy[:, :n])
    done = time.perf_counter()
    return {"import": imported - start, "load": loaded - imported, "assemble": done - loaded,
            "total": done - imported, "stages": len(prob.stages), "chunks": lengths}


def run(ctx: Run) -> JobSummary:
    """Load + assemble of both problems at every N."""
    assemble = {}
    for problem in PROBLEMS:
        for n in ctx.settings.sizes:
            assemble[(problem, n)] = run_child({"kind": NAME, "problem": problem, "n": n},
                                               ctx.settings, timeout=300)
    ctx.report["assemble"] = assemble
    note = ", ".join(f"{p} N={fmt_n(n)}: {r.get('total', float('nan')):.3f}"
                     for (p, n), r in assemble.items())
    say("== load + assemble (s): " + note)
    return summarise(NAME, list(assemble.values()), f"load + assemble (s): {note}")
