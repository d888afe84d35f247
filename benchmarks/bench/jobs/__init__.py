"""The ten jobs of a run, in the order they run, and their child sides by kind.

Each job module has ``NAME``, ``run(ctx) -> JobSummary`` (the parent's side, which fills
``ctx.report``) and, if it starts children, ``child(job) -> dict`` (the child's side).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from . import (
    assemble,
    blas,
    data,
    fleet,
    hugelog,
    improve,
    profile,
    solve,
    starts,
    startup,
)

#: The jobs in the order a run runs them (``solve`` last: its budget is what is left).
JOBS = (starts, startup, assemble, data, profile, blas, fleet, hugelog, improve, solve)

#: Child functions by the ``kind`` of a job description.
CHILDREN: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    starts.NAME: starts.child, solve.NAME: solve.child, assemble.NAME: assemble.child,
    profile.NAME: profile.child, data.NAME: data.child, fleet.NAME: fleet.child,
    startup.NAME: startup.child, hugelog.NAME: hugelog.child, improve.NAME: improve.child,
}
