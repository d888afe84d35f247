"""What is benchmarked, and the settings and shared state of one run."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from .measure import Clock

ROOT = Path(__file__).resolve().parents[2]
HERE = ROOT / "benchmarks"
#: The entry point; children are started as ``python RUN --child JSON``.
RUN = HERE / "run.py"
#: Prefix of the line on which a child prints its JSON result.
MARK = "BENCH-RESULT "
SEED = 1
DEFAULT_SIZES = (1_000, 10_000, 100_000, 1_000_000)
#: Sizes of ``--quick``: tiny, so that every job runs in seconds.
QUICK_SIZES = (200,)

PROBLEMS: dict[str, dict[str, Any]] = {
    "linear": {
        "path": "problems/platen_self_calibration.yaml",
        "scenario": "problems/scenarios/courier_platen.yaml",
        "title": "§3.1 platen self-calibration: linear, 36 parameters, cost Σ g_p²",
        "methods": ("symcal", "symcal_public", "floor", "ls_trf_jax", "ls_trf_casadi",
                    "ls_lm_casadi", "ceres", "optimistix", "least_squares", "bfgs",
                    "symcal_analysis"),
    },
    "dual": {
        "path": "problems/dual_sensor_calibration.yaml",
        "scenario": "problems/scenarios/courier_dual.yaml",
        "title": "§3.2 dual-sensor calibration: nonlinear, 49 parameters, "
                 "cost Σ g_x² + g_y² + g_p²",
        "methods": ("symcal", "symcal_public", "symcal_serial", "symcal_ipopt",
                    "ls_trf_jax", "ls_trf_casadi", "ls_lm_casadi", "ceres", "optimistix",
                    "least_squares", "bfgs", "symcal_analysis"),
    },
}

LABELS = {
    "symcal": "symcal (default path)",
    "symcal_public": "symcal.solve (public API, whole solve)",
    "ls_trf_jax": "scipy least_squares trf, JAX Jacobian",
    "ls_trf_casadi": "scipy least_squares trf, CasADi Jacobian",
    "ls_lm_casadi": "scipy least_squares lm (MINPACK), CasADi Jacobian",
    "ceres": "Ceres (pyceres) LM, dense QR, CasADi Jacobian",
    "optimistix": "optimistix LevenbergMarquardt (jax.jit)",
    "symcal_serial": "symcal, 1 thread, interpreted",
    "symcal_ipopt": "symcal, IPOPT path",
    "floor": "numpy Γ + lstsq (floor)",
    "least_squares": "scipy least_squares, FD Jacobian",
    "bfgs": "scipy BFGS, FD gradient",
    "symcal_analysis": "symcal run_stage (solver + stage analysis)",
}
#: Rows that are never skipped: the issue's targets are about them.
UNCAPPED = {"symcal", "symcal_public", "floor"}
#: symcal's rows: their cold time is taken in a fresh process with an empty compile cache.
SYMCAL_ROWS = {"symcal", "symcal_public", "symcal_serial", "symcal_ipopt", "symcal_analysis"}
#: The exact-Jacobian peers (issue 26), optional: ``pip install -e ".[bench]"``.
EXACT_PEERS = ("ls_trf_jax", "ls_trf_casadi", "ls_lm_casadi", "ceres", "optimistix")
#: A peer is not started where its peak memory, extrapolated linearly from the previous
#: size, would pass this (MiB): the machine is shared, and a 3N × 49 Jacobian at N = 1e6
#: is 1.1 GiB before the solvers' copies of it.
MEMORY_CAP_MIB = 8_192

#: Data and start files of every (problem, N): {"data": NPZ path, "start": NPY path}.
Files = dict[tuple[str, int], dict[str, str]]


@dataclasses.dataclass(frozen=True)
class Settings:
    """The options of one run (see ``bench.cli.parse_args``)."""

    sizes: tuple[int, ...]
    repeats: int
    cap: float
    repeat_budget: float
    budget: float
    blas_threads: str | None
    out: Path | None
    quick: bool
    jobs: tuple[str, ...] = ()
    methods: tuple[str, ...] = ()


@dataclasses.dataclass
class Run:
    """Everything the jobs of one run share.

    Attributes
    ----------
    settings
        The run's options.
    workdir
        Temporary directory of the simulated data.
    files
        Data and start file of every (problem, N).
    report
        The measurements, filled in by the jobs; rendered into RESULTS.md.
    clock
        The run's wall-clock budget.
    """

    settings: Settings
    workdir: Path
    files: Files
    report: dict[str, Any]
    clock: Clock
