"""Shared fixtures: paths, and small model-consistent courier data made with numpy only."""

from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread, symcal's own default, which would not apply here: numpy is imported
# before symcal (threads on these tall, skinny problems made the suite 2.5x slower).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RHO = 1.016
F = 2 * np.pi / RHO
L_S = 9.7
L_O = 4.85
HARMONICS = (1, 2, 4, 6)


def basis(p: np.ndarray) -> np.ndarray:
    """The nine eq. (3) regressors of a segment reading (independent of symcal)."""
    cols = [np.ones_like(p)]
    for h in HARMONICS:
        cols += [np.sin(h * F * p), np.cos(h * F * p)]
    return np.column_stack(cols)


def courier_data(n: int, k: np.ndarray, noise: float, seed: int) -> dict[str, np.ndarray]:
    """Scatter poses and readings with p̄ + e(p̄) = p* exactly, plus Gaussian noise.

    ``k`` is 4 × 9 (segments 1..4, eq. 3 coefficients); small enough for a contraction.
    """
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 10 * RHO, n), rng.uniform(0, 10 * RHO, n)
    th = np.deg2rad(rng.uniform(-0.5, 0.5, n))
    c, s = np.cos(th), np.sin(th)
    true = [x - L_O * c + L_S / 2 * s, y + L_S / 2 * s - L_O * c,
            x + L_O * c - L_S / 2 * s, y - L_S / 2 * s + L_O * c]
    cols = {"t": np.arange(n) * 0.1}
    for i in range(4):
        pb = true[i].copy()
        for _ in range(100):
            pb = true[i] - basis(pb) @ k[i]
        cols[f"p{i + 1}"] = pb + rng.normal(0, noise, n)
    cols.update(x_ref=x, y_ref=y, theta_ref=th)
    return cols


@pytest.fixture
def root() -> Path:
    """The repository root."""
    return ROOT


@pytest.fixture
def true_k() -> np.ndarray:
    """Eq. (3) coefficients of the four segments (mm), a few µm each."""
    rng = np.random.default_rng(42)
    k = rng.normal(0, 0.004, (4, 9)) / np.array([1, 1, 1, 2, 2, 4, 4, 6, 6])
    return k


def write_csv(path: Path, cols: dict[str, np.ndarray]) -> Path:
    """Write columns as CSV with a header."""
    with path.open("w") as fh:
        fh.write(",".join(cols) + "\n")
        np.savetxt(fh, np.column_stack(list(cols.values())), delimiter=",", fmt="%.15g")
    return path


def magnetometer_gain_time(folder: Path) -> Path:
    """The acceptance's tumbled magnetometer copied into ``folder`` with its data
    simulated with the x gain growing in time (``scenario_gain_time.yaml``); returns its
    problem file."""
    source = ROOT / "tests" / "acceptance" / "magnetometer"
    (folder / "models").mkdir()
    (folder / "models" / "magnetometer.yaml").write_text(
        (source / "models" / "magnetometer.yaml").read_text())
    for name in ("problem.yaml", "scenario.yaml", "scenario_gain_time.yaml"):
        (folder / name).write_text((source / name).read_text())
    (folder / "problem_free.yaml").write_text(
        (source / "problem_free.yaml").read_text().replace("scenario.yaml",
                                                           "scenario_gain_time.yaml"))
    return folder / "problem.yaml"


def simulated(scenario, seed: int, runs: tuple[str, ...] = ("calibration", "validation")
              ) -> dict:
    """The runs of a loaded scenario simulated with ``seed``, as datasets by name."""
    from symcal.data.dataset import make_dataset
    from symcal.simulation import simulate_run

    return {k: make_dataset(k, "simulated", simulate_run(scenario, k, seed), []) for k in runs}


def with_effect(folder: Path, effect: str):
    """``folder``'s ``scenario.yaml`` with its hidden effect ``effect`` switched on."""
    from symcal.simulation import load_scenario

    return load_scenario(folder / "scenario.yaml").overlay({"effects": {effect: {"on": True}}})
