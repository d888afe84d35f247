"""Standard errors of equal (and estimated) weighting where the declared noise differs
between rows: the sandwich with each row's propagated covariance
(:mod:`symcal.analysis.declared_errors`), against numpy, a Monte Carlo, and the passes
over shards."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from test_hugelog import write_shards

import symcal
from symcal.analysis import floors
from symcal.analysis.serial import detect
from symcal.calibrate.partitioned import solve_partitioned
from symcal.data.dataset import make_dataset
from symcal.solvers.executor import SerialExecutor

R, V0 = 10.0, 0.3
SV, SI = 0.05, 0.005

OHM = """\
problem: ohm
doc: a resistor read by a voltmeter with an offset and an ammeter
columns:
  t: {{unit: s, role: time}}
  V: {{unit: V{v_noise}}}
  I: {{unit: A, noise: 0.005 A}}
weighting: {weighting}
parameters:
  R: {{value: 9, unit: ohm, scale: 0.1}}
  v0: {{value: 0, unit: V, scale: 0.05}}
constraints:
  g: {{expr: (V - v0)/I - R, unit: ohm}}
datasets:
  calibration: {{path: cal.csv, role: fit}}
"""


def _problem(tmp_path: Path, weighting: str = "equal", v_noise: str = ", noise: 0.05 V"
             ) -> symcal.Problem:
    path = tmp_path / f"ohm-{weighting}{'' if v_noise else '-undeclared'}.yaml"
    path.write_text(textwrap.dedent(OHM.format(weighting=weighting, v_noise=v_noise)))
    return symcal.load_problem(path)


def _columns(seed: int, n: int = 2000) -> dict[str, np.ndarray]:
    """A current swept from 0.3 A to 2 A: the ratio's noise is 7 times larger at the
    bottom of the sweep than at the top."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    i = 0.3 + 1.7 * (0.5 - 0.5 * np.cos(2 * np.pi * t / 37.0))
    v = R * i + V0 + rng.normal(size=n) * SV
    return {"t": t, "V": v, "I": i + rng.normal(size=n) * SI}


def _data(seed: int) -> dict[str, symcal.Dataset]:
    return {"calibration": make_dataset("calibration", "sim", _columns(seed), ["t", "V", "I"])}


def _numpy(cols: dict[str, np.ndarray], r: float, v0: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """The sandwich and the pooled covariance of (R, v0) at the estimate, numpy alone:
    g = (V − v0)/I − R, ∂g/∂(R, v0) = (−1, −1/I), var g = (σ_V² + (g + R)² σ_I²)/I²."""
    v, i = cols["V"], cols["I"]
    g = (v - v0) / i - r
    jac = np.column_stack([-np.ones_like(i), -1 / i])
    var = (SV**2 + ((v - v0) / i) ** 2 * SI**2) / i**2
    a_inv = np.linalg.inv(jac.T @ jac)
    meat = jac.T @ (var[:, None] * jac)
    rss = float(g @ g)
    factor = rss / (np.sum(var) - np.trace(a_inv @ meat))
    return factor * a_inv @ meat @ a_inv, rss / (len(g) - 2) * a_inv


def test_sandwich_equals_numpy_and_differs_from_pooled(tmp_path: Path) -> None:
    problem = _problem(tmp_path)
    data = _data(1)
    result = symcal.solve(problem, data)
    assert not result.stages[-1].serial.detected     # else the Newey-West sandwich
    cols = {k: np.asarray(v) for k, v in data["calibration"].columns.items()}
    cov, pooled = _numpy(cols, result.params["R"].value, result.params["v0"].value)
    se = np.array([result.params["R"].se, result.params["v0"].se])
    np.testing.assert_allclose(se, np.sqrt(np.diag(cov)), rtol=1e-6)
    assert np.sqrt(pooled[1, 1] / cov[1, 1]) < 0.8       # the pooled v0 error: too small
    note = next(n for n in result.stages[-1].notes if n.startswith("standard errors:"))
    assert "each observation's covariance propagated from the readings' declared noise" in note
    ratio = np.sqrt(np.diag(pooled) / np.diag(cov))
    assert f"off by up to a factor {max(ratio.max(), 1 / ratio.min()):.2g}" in note


def test_monte_carlo_spread_matches_the_standard_errors(tmp_path: Path) -> None:
    """Over 120 seeds the estimates' spread is the sandwich's standard error within the
    spread's own sampling error (about 6.5 %; the pooled v0 error was 31 % below it)."""
    problem = _problem(tmp_path)
    est, se = [], []
    for seed in range(120):
        res = symcal.solve(problem, _data(100 + seed))
        est.append([res.params["R"].value, res.params["v0"].value])
        se.append([res.params["R"].se, res.params["v0"].se])
    spread = np.std(np.array(est), axis=0, ddof=1)
    ratio = np.mean(np.array(se), axis=0) / spread
    assert np.all(np.abs(ratio - 1) < 0.2), ratio


def test_the_floors_reuse_the_stage_sums(tmp_path: Path, monkeypatch) -> None:
    """One pass of the share's sums for the stage's errors and the floors of its fit."""
    calls: list[str] = []
    sums = floors.SharePlan.sums

    def counted(self, ds, theta):
        calls.append(ds.name)
        return sums(self, ds, theta)

    monkeypatch.setattr(floors.SharePlan, "sums", counted)
    result = symcal.solve(_problem(tmp_path), _data(3))
    assert calls == ["calibration"]
    assert result.floor_tests[0].dof > 0


def test_undeclared_noise_keeps_the_pooled_variance(tmp_path: Path) -> None:
    """A reading without declared noise: no covariance per row to take, s² A⁻¹ as ever."""
    problem = _problem(tmp_path, v_noise="")
    data = _data(1)
    result = symcal.solve(problem, data)
    assert not result.stages[-1].serial.detected
    cols = {k: np.asarray(v) for k, v in data["calibration"].columns.items()}
    _, pooled = _numpy(cols, result.params["R"].value, result.params["v0"].value)
    se = np.array([result.params["R"].se, result.params["v0"].se])
    np.testing.assert_allclose(se, np.sqrt(np.diag(pooled)), rtol=1e-6)
    assert not any(n.startswith("standard errors:") for n in result.stages[-1].notes)


def test_propagated_weighting_is_unchanged(tmp_path: Path) -> None:
    """Weights by each row's own covariance already: no sandwich note."""
    result = symcal.solve(_problem(tmp_path, "propagated"), _data(7))
    assert not any(n.startswith("standard errors:") for n in result.stages[-1].notes)


def test_shards_give_the_errors_of_the_data_in_memory(tmp_path: Path) -> None:
    problem = _problem(tmp_path)
    cols = _columns(11, 3000)
    folder = write_shards(tmp_path / "log #1", cols, "npz", (1000, 1200, 800))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    memory = symcal.solve(problem, {"calibration": make_dataset(
        "calibration", "sim", cols, ["t", "V", "I"])})
    for name in ("R", "v0"):
        assert sharded.params[name].se == pytest.approx(memory.params[name].se, rel=1e-9)
    assert any(n.startswith("standard errors:") for n in sharded.stages[-1].notes)


def test_serial_detection_holds_its_level_on_rows_of_unequal_noise() -> None:
    """Independent residuals whose variance follows the sweep (44-fold): the detection
    at 1 % names serial correlation on about 1 % of 600 datasets; ``√N·ρ̂`` against the
    same threshold does on about 12 %."""
    n = 2000
    t = np.arange(n) * 0.1
    sd = 1 / (0.3 + 1.7 * (0.5 - 0.5 * np.cos(2 * np.pi * t / 37.0)))
    rng = np.random.default_rng(2)
    found, naive = 0, 0
    for _ in range(600):
        serial = detect(("g",), (rng.normal(size=n) * sd)[:, None])
        found += serial.detected
        naive += abs(serial.rho[0]) * np.sqrt(n) > serial.threshold
    assert found <= 15 and naive >= 40, (found, naive)
