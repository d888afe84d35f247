"""Two members that are one fit written two ways get no ``symcal design`` suggestion (a
new user's flow loop: an ultrasonic meter's density law ``rho0*(1 - beta*(T - T0))``
with its gain free makes freeing T0 the same fit as freeing beta; symcal offered an
experiment to separate them)."""

from __future__ import annotations

import numpy as np
import pytest
from test_gauge_dismissed import MODELS

import symcal
from symcal.data.dataset import make_dataset
from symcal.revise.improve import SAME_WORDS

BETA = 2.6e-4         # the ultrasonic meter's fluid expands more than its model says


def _dwells(name: str, seed: int) -> symcal.Dataset:
    rng = np.random.default_rng(seed)
    n = 600
    m = np.repeat(rng.uniform(1, 10, 20), 30)
    temp = np.repeat(rng.uniform(283, 343, 20), 30)
    volume = m / (998.2 * (1 - 2.07e-4 * (temp - 293.15)))          # m³/s, the turbine's
    q = (volume * 60000 + 0.8) / 1.012
    u = (m / (998.2 * (1 - BETA * (temp - 293.15))) * 3600 - 0.12) / 0.985
    return make_dataset(name, "test", {
        "t": np.arange(n, dtype=float), "m_c": m + rng.normal(0, 0.002, n),
        "q_t": q + rng.normal(0, 0.5, n), "u_us": u + rng.normal(0, 0.05, n),
        "T": temp + rng.normal(0, 0.05, n)}, [])


def _write(tmp_path) -> dict[str, symcal.Dataset]:
    """The flow loop's files with a validation run, and both runs' data."""
    for name, text in MODELS.items():
        (tmp_path / name).write_text(text.replace(
            "  calibration: {path: calibration.csv}\n",
            "  calibration: {path: calibration.csv}\n  validation: {path: validation.csv}\n"))
    return {"calibration": _dwells("calibration", 1), "validation": _dwells("validation", 2)}


@pytest.mark.slow
def test_one_fit_written_two_ways_gets_no_experiment(tmp_path) -> None:
    data = _write(tmp_path)
    result = symcal.improve(tmp_path / "fixed.yaml", tmp_path / "out", data)
    notes = result.rounds[1].notes()
    pair = {"us's beta is off", "us's T0 is off"}
    assert result.rounds[1].added in pair
    other = (pair - {result.rounds[1].added}).pop()
    said = [n for n in notes if f"from {other} (" in n]
    assert len(said) == 1 and said[0].endswith(SAME_WORDS)
    assert "symcal design" not in said[0]


@pytest.mark.slow
def test_improve_takes_a_loaded_problem(tmp_path) -> None:
    """As solve does (a new user's script passed the Problem it had loaded and got a
    TypeError from pathlib)."""
    data = _write(tmp_path)
    by_path = symcal.improve(tmp_path / "fixed.yaml", tmp_path / "a", data)
    loaded = symcal.improve(symcal.load_problem(tmp_path / "fixed.yaml"), tmp_path / "b", data)
    assert [r.added for r in loaded.rounds] == [r.added for r in by_path.rounds]
    assert [r.problem_file.name for r in loaded.rounds[1:]] == ["fixed_round1.yaml"]
    np.testing.assert_allclose(loaded.rounds[-1].result.theta, by_path.rounds[-1].result.theta,
                               rtol=1e-12)
