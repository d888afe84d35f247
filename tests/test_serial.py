"""Serially correlated rows (issue 22 item 3): detected on time-ordered rows, reported,
and allowed for in the standard errors (Newey-West), checked by fitting the two halves of
a recording: their difference must be consistent with the stated errors."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

import symcal
import symcal.calibrate.solve
from symcal.analysis.serial import bandwidth, hac_meat
from symcal.data.dataset import make_dataset
from symcal.report.text import text_report

GAUGE = """\
model: gauge
inputs:
  r: {unit: mm, noise: 10 um, doc: raw reading}
parameters:
  c: {value: 0, unit: mm, scale: 0.1, doc: offset}
  k: {value: 0, unit: 1, scale: 0.01, doc: gain error}
outputs:
  x_hat: {expr: c + (1 + k)*r, unit: mm}
"""

PROBLEM = """\
problem: two_gauges
doc: a gauge calibrated against another one that reads the same position
instances:
  s: {model: gauge.yaml, inputs: {r: b}}
constraints:
  g: {expr: s.x_hat - a, unit: um}
columns:
  t: {unit: s, role: time}
  a: {unit: mm, noise: 10 um}
  b: {unit: mm}
datasets:
  calibration: {path: data.csv}
"""


@pytest.fixture(scope="module")
def problem(tmp_path_factory) -> symcal.Problem:
    folder = tmp_path_factory.mktemp("gauges")
    (folder / "gauge.yaml").write_text(textwrap.dedent(GAUGE))
    (folder / "two.yaml").write_text(textwrap.dedent(PROBLEM))
    return symcal.load_problem(folder / "two.yaml")


def _ar1(rng: np.random.Generator, n: int, rho: float, sd: float) -> np.ndarray:
    """An AR(1) series of marginal standard deviation ``sd``."""
    out = np.empty(n)
    out[0] = rng.normal(0, sd)
    step = rng.normal(0, sd * np.sqrt(1 - rho**2), n)
    for i in range(1, n):
        out[i] = rho * out[i - 1] + step[i]
    return out


def _recording(seed: int, rho: float, n: int = 2000) -> dict[str, np.ndarray]:
    """A slow recording: the position swings 5 mm (period 10 s, 10 Hz); each gauge's noise
    is 10 µm with lag-1 autocorrelation ``rho`` (the declared, marginal, noise)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    x = 5 * np.sin(2 * np.pi * t / 10.0)
    return {"t": t, "a": x + _ar1(rng, n, rho, 0.01),
            "b": (x - 0.05) / 1.002 + _ar1(rng, n, rho, 0.01)}


def _halves(problem: symcal.Problem, cols: dict[str, np.ndarray]) -> list[symcal.Result]:
    n = len(cols["t"])
    return [symcal.solve(problem, {"calibration": make_dataset(
        "calibration", "half", {k: v[part] for k, v in cols.items()}, [])})
        for part in (slice(0, n // 2), slice(n // 2, n))]


def _z(results: list[symcal.Result]) -> list[float]:
    out = []
    for name in ("s.c", "s.k"):
        one, two = (r.params[name] for r in results)
        out.append((one.value - two.value) / float(np.hypot(one.se, two.se)))
    return out


def test_hac_meat_equals_the_direct_sum() -> None:
    """Chunk by chunk with the last L rows carried equals numpy's double sum."""
    rng = np.random.default_rng(0)
    scores = rng.normal(size=(500, 3)) + np.cumsum(rng.normal(size=(500, 3)), axis=0) * 0.1
    lags = 7
    direct = scores.T @ scores
    for lag in range(1, lags + 1):
        cross = scores[:-lag].T @ scores[lag:]
        direct += (1 - lag / (lags + 1)) * (cross + cross.T)
    for size in (1, 5, 7, 64, 500):
        parts = (scores[i:i + size] for i in range(0, 500, size))
        np.testing.assert_allclose(hac_meat(parts, lags, 3), direct, rtol=1e-12, atol=1e-9)
    assert bandwidth(0.0, 1000) == 1 and bandwidth(0.8, 1000) == 31
    assert bandwidth(0.999, 100) == 25          # at most N/4


def test_correlated_rows_are_detected_and_reported(problem, tmp_path) -> None:
    (first, _) = _halves(problem, _recording(3, 0.8))
    serial = first.stages[-1].serial
    assert serial is not None and serial.detected
    assert 0.7 < serial.rho[0] < 0.9
    assert serial.lags == bandwidth(serial.rho[0], 1000) == 33
    text = text_report(first)
    assert "  the residuals are serially correlated (lag-1 autocorrelation +0." in text
    assert "the Newey-West sandwich over 33 lags: the rows are serially correlated" in text
    doc = first.to_dict()["stages"][-1]["serial_correlation"]
    assert doc["detected"] is True and doc["lags"] == 33
    loaded = symcal.Result.load(first.save(tmp_path / "result.json"))
    assert loaded.stages[-1].serial == serial
    # rows in random order are not a recording: nothing is tested
    shuffled = _recording(3, 0.8)
    shuffled["t"] = shuffled["t"][::-1].copy()
    result = symcal.solve(problem, {"calibration": make_dataset("calibration", "x",
                                                                shuffled, [])})
    assert result.stages[-1].serial is None


@pytest.mark.slow
def test_two_halves_of_a_recording_agree_within_the_stated_errors(problem,
                                                                  monkeypatch) -> None:
    """30 recordings with noise of lag-1 autocorrelation 0.8, each fitted in two halves:
    with the Newey-West errors the mean square of (half 1 - half 2)/√(se1² + se2²) over
    both parameters is 1.05 (measured; 1 expected, ±0.26 at 95 % for 60 values); with
    errors as if the rows were independent it is 7.6 (the test this check can fail)."""
    z = [v for seed in range(30) for v in _z(_halves(problem, _recording(seed, 0.8)))]
    assert 0.6 < float(np.mean(np.square(z))) < 1.5
    monkeypatch.setattr(symcal.calibrate.solve, "time_ordered", lambda *_: False)
    naive = [v for seed in range(30) for v in _z(_halves(problem, _recording(seed, 0.8)))]
    assert float(np.mean(np.square(naive))) > 4


@pytest.mark.slow
def test_independent_rows_are_rarely_called_correlated(problem) -> None:
    """White noise: the detection's false-alarm rate is its level (1 %): 60 halves,
    measured 1; more than 4 has probability 0.003."""
    found = [r.stages[-1].serial.detected for seed in range(30)
             for r in _halves(problem, _recording(seed, 0.0))]
    assert sum(found) <= 4
    z = [v for seed in range(30) for v in _z(_halves(problem, _recording(seed, 0.0)))]
    assert 0.6 < float(np.mean(np.square(z))) < 1.5


ABBE = GAUGE.replace("  k: {value: 0, unit: 1, scale: 0.01, doc: gain error}\n",
                     "  k: {value: 0, unit: 1, scale: 0.01, doc: gain error}\n"
                     "  d: {value: 0, unit: mm/rad, scale: 10, doc: Abbe offset}\n"
                     ).replace("  r: {unit: mm, noise: 10 um, doc: raw reading}\n",
                               "  r: {unit: mm, noise: 10 um, doc: raw reading}\n"
                               "  w: {unit: rad, doc: pitch}\n"
                               ).replace("c + (1 + k)*r", "c + (1 + k)*r + d*w")


def test_newey_west_errors_keep_every_direction(tmp_path) -> None:
    """The Newey-West meat of a gauge with an Abbe term (its pitch 2e-5 rad against a
    5 mm swing: the sum of the scores' products spans 1e13 in the parameters' units) gives
    the standard errors of numpy's sandwich, computed in scaled coordinates: the sum was
    cut at 1e-9 of its largest eigenvalue, which dropped part of the Abbe direction and
    stated its error 10 times too small (6.0 against 58.8 mm/rad)."""
    (tmp_path / "gauge.yaml").write_text(ABBE)
    (tmp_path / "two.yaml").write_text(PROBLEM.replace(
        "  s: {model: gauge.yaml, inputs: {r: b}}",
        "  s: {model: gauge.yaml, inputs: {r: b, w: w}}").replace(
        "  b: {unit: mm}\n", "  b: {unit: mm}\n  w: {unit: rad}\n"))
    cols = _recording(5, 0.8)
    rng = np.random.default_rng(6)
    cols["w"] = 2e-5 * np.sin(2 * np.pi * cols["t"] / 7.3 + 1.0) + rng.normal(0, 2e-6, 2000)
    cols["b"] = cols["b"] - 30.0 * cols["w"] / 1.002
    result = symcal.solve(tmp_path / "two.yaml", {"calibration": make_dataset(
        "calibration", "abbe", cols, [])})
    serial = result.stages[-1].serial
    assert serial is not None and serial.detected
    names = ["s.c", "s.k", "s.d"]
    c, k, d = (result.params[n].value for n in names)
    # residual g = c + (1 + k) b + d w - a (mm); its Jacobian [1, b, w]; the sandwich
    # with Bartlett weights over the stated lags, times rows/(rows - 3)
    jac = np.column_stack([np.ones(2000), cols["b"], cols["w"]])
    g = c + (1 + k) * cols["b"] + d * cols["w"] - cols["a"]
    scale = 1 / np.linalg.norm(jac, axis=0)
    js = jac * scale
    scores = js * g[:, None]
    lags = serial.lags
    meat = scores.T @ scores
    for lag in range(1, lags + 1):
        cross = scores[:-lag].T @ scores[lag:]
        meat += (1 - lag / (lags + 1)) * (cross + cross.T)
    bread = np.linalg.inv(js.T @ js)
    cov = bread @ meat @ bread * 2000 / 1997 * np.outer(scale, scale)
    expected = np.sqrt(np.diag(cov))
    stated = np.array([result.params[n].se for n in names])
    np.testing.assert_allclose(stated, expected, rtol=1e-6)
