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


def divider_run(n: int, seed: int, period_t: float, period_v: float, phase: float,
                heating: float | None = None, zero: float = 0.0) -> dict[str, np.ndarray]:
    """An NTC thermistor (R25 10.03 kΩ, β 3935 K) below a 10 kΩ resistor under a supply
    switched between about 1 and 5.5 V, against a reference thermometer in a bath swept
    2-58 °C (a reviewer's simulation; ``tests/data/divider``): heated by its own Vth²/R
    where ``heating`` (its dissipation constant, W/K) is given, its voltage read ``zero``
    volts high (an ADC channel's zero)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 5.0
    bath = 273.15 + 30 + 28 * np.sin(2 * np.pi * t / period_t + phase)
    vs = (3.25 + 1.125 * np.tanh(15 * np.sin(2 * np.pi * t / period_v))
          + 0.75 * np.tanh(15 * np.sin(2 * np.pi * t / (period_v * 2.7))))
    temp = bath.copy()
    for _ in range(50 if heating is not None else 1):     # the heated part's temperature
        r = 10.03 * np.exp(3935.0 * (1 / temp - 1 / 298.15))
        vth = vs * r / (r + 10.0)
        if heating is not None:
            temp = bath + vth**2 / (r * 1e3) / heating
    return {"t": t, "Vth": vth + zero + rng.normal(size=n) * 1e-4,
            "Vs": vs + rng.normal(size=n) * 1e-4, "Tr": bath + rng.normal(size=n) * 0.01}


def divider_data(seed: int = 1, heating: float | None = None, zero: float = 0.0) -> dict:
    """The divider's calibration (3000 rows) and held-out validation (1500) runs of
    :func:`divider_run`, as datasets by name."""
    from symcal.data.dataset import make_dataset

    runs = {"calibration": divider_run(3000, seed, 9000, 1100, 0.0, heating, zero),
            "validation": divider_run(1500, seed + 100, 5000, 700, 1.0, heating, zero)}
    return {k: make_dataset(k, "simulated", v, []) for k, v in runs.items()}
