"""Job ``blas``: the same solves with one BLAS thread and with the library's default."""

from __future__ import annotations

from typing import Any

from ..children import run_child
from ..config import Run
from ..fmt import fmt_n, say
from .base import JobSummary, summarise
from .solve import solve_job

NAME = "blas"
SETTINGS = (("1 thread", "1"), ("BLAS default", None))


def jobs(ctx: Run) -> list[tuple[str, str, int]]:
    """(problem, method, N) compared: four in a full run, symcal's dual solve in a quick
    one."""
    sizes = ctx.settings.sizes
    n0 = min(sizes)
    if ctx.settings.quick:
        return [("dual", "symcal", n0)]
    n_lin = 100_000 if 100_000 in sizes else n0
    return [("dual", "symcal", n0), ("dual", "least_squares", n0),
            ("linear", "symcal", n_lin), ("linear", "floor", n_lin)]


def run(ctx: Run) -> JobSummary:
    """Each job of :func:`jobs` pinned to one thread, then with the variables unset."""
    sens: dict[tuple[str, str, str, int], dict[str, Any]] = {}
    for label, threads in SETTINGS:
        for problem, method, n in jobs(ctx):
            job = solve_job(ctx, problem, method, n, ctx.settings.cap, repeats=3,
                            repeat_budget=10)
            sens[(label, problem, method, n)] = run_child(job, ctx.settings, timeout=600,
                                                          threads=threads)
    ctx.report["blas"] = sens
    note = ", ".join(f"{lab} {p} {m} N={fmt_n(n)}: {r.get('seconds', float('nan')):.3f} s"
                     for (lab, p, m, n), r in sens.items())
    say("== BLAS threads: " + note)
    return summarise(NAME, list(sens.values()), note)
