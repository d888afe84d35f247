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
        "methods": ("symcal", "floor", "least_squares", "bfgs", "symcal_analysis"),
    },
    "dual": {
        "path": "problems/dual_sensor_calibration.yaml",
        "scenario": "problems/scenarios/courier_dual.yaml",
        "title": "§3.2 dual-sensor calibration: nonlinear, 49 parameters, "
                 "cost Σ g_x² + g_y² + g_p²",
        "methods": ("symcal", "symcal_serial", "symcal_ipopt", "least_squares", "bfgs",
                    "symcal_analysis"),
    },
}

LABELS = {
    "symcal": "symcal (default path)",
    "symcal_serial": "symcal, 1 thread, interpreted",
    "symcal_ipopt": "symcal, IPOPT path",
    "floor": "numpy Γ + lstsq (floor)",
    "least_squares": "scipy least_squares, FD Jacobian",
    "bfgs": "scipy BFGS, FD gradient",
    "symcal_analysis": "symcal run_stage (solver + stage analysis)",
}
#: Rows that are never skipped: the issue's targets are about them.
UNCAPPED = {"symcal", "floor"}

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
