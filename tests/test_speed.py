"""Issue 26: the solve as fast as the solver, without changing what it finds.

The lm path's stop at the rounding of the cost, blocked QR in the TSQR passes, BLAS threads
limited around symcal's own passes whatever the import order, and the compiled twin built
when it pays.  Every test compares with an independent computation or with the behaviour
the change replaced; none asserts a time.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.solvers import trust_region

DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"


def _runs(lines: list[str]) -> list[list[float]]:
    """The ratios of every lm run's trial steps, one list per run (iterations restart)."""
    runs: list[list[float]] = []
    for line in lines:
        m = re.search(r"iteration +(\d+) .* ratio (\S+)$", line)
        if m is None:
            continue
        if int(m.group(1)) == 1:
            runs.append([])
        runs[-1].append(float(m.group(2)))
    return runs


def test_lm_stops_at_the_rounding_of_the_cost_without_a_train_of_rejections(monkeypatch):
    """The dual problem's last stage reaches its optimum in a few steps; then the cost can
    no longer tell steps apart.  Two rejected trials measure that and the solve stops
    (before: 17 and 11 trials, trains of 13 and 9 rejections); the estimate is the one the
    old stop reached, to far below its standard errors."""
    problem = symcal.load_problem(DUAL)
    lines: list[str] = []
    fast = symcal.solve(problem, progress=lines.append)
    assert fast.success
    runs = _runs(lines)
    full = runs[-2:]                      # the last stage: equal weights, then whitened
    for ratios in full:
        trailing = len(ratios) - max(i + 1 for i, r in enumerate(ratios)
                                     if r > trust_region.ACCEPT)
        assert trailing <= 2, ratios
    assert fast.stages[-1].status == "converged_to_rounding"
    # the stop it replaced: shrink the region until it collapses
    monkeypatch.setattr(trust_region._Steps, "settled", lambda self: False)
    old_lines: list[str] = []
    old = symcal.solve(problem, progress=old_lines.append)
    assert old.success
    assert sum(map(len, _runs(old_lines)[-2:])) > sum(map(len, full))
    for p in fast.parameters:
        if p.se is not None:
            assert abs(p.value - old.params[p.name]) <= 1e-6 * p.se, p.name


# ------------------------------------------------------------------ BLAS threads

BLAS_PROBE = """
import json
import sys

import numpy as np                         # first, as most scripts do
import scipy.linalg
from threadpoolctl import threadpool_info

import symcal
from symcal.solvers.executor import blas_limit
from symcal.solvers.instrument import counting


def blas():
    return sorted({d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"})


before = blas()
with blas_limit():
    inside = blas()
after = blas()
during = []
with counting(on_iteration=lambda *a: during.extend(blas())):
    result = symcal.solve(sys.argv[1])
print(json.dumps([before, inside, after, sorted(set(during)), blas(), result.success]))
"""


@pytest.mark.parametrize("threads", [None, "3"])
def test_blas_is_held_inside_symcals_passes_whatever_the_import_order(threads) -> None:
    """numpy imported before symcal, no BLAS variable set (OpenBLAS then starts one thread
    per core): inside symcal's passes and solver steps BLAS has one thread, and the
    program's own setting is back afterwards; a user's OPENBLAS_NUM_THREADS is obeyed."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    if threads:
        env["OPENBLAS_NUM_THREADS"] = threads
    out = subprocess.run([sys.executable, "-c", BLAS_PROBE,
                          str(ROOT / "tests" / "nist" / "Misra1a.start1.yaml")],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    before, inside, after, during, end, success = json.loads(out.stdout.splitlines()[-1])
    want = [int(threads)] if threads else [1]
    assert inside == want and during == want, (before, inside, during)
    assert after == before and end == before and success
