"""Gauges of every sign (issue 24 item 4): a scale whose parameters enter with opposite
powers is named a scale; a collapse onto a trivial point is a failed solve whatever the
gauge was called; gauges that share parameters are one fix set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import symcal
from symcal.cli import main

SIGNS = """\
problem: signs
columns:
  w: {unit: rad/s}
  gyro: {unit: rad/s}
parameters:
  b: {value: 0.3, unit: m, scale: 0.3}
  k: {value: 1.0, scale: 1.0}
  L: {value: 0.2, unit: m, fixed: true}
constraints:
  g: {expr: L*w/b - k*gyro, unit: rad/s}
datasets:
  calibration: {path: data.csv}
"""

DRIVE = """\
problem: drive
columns:
  w_l: {unit: rad/s}
  w_r: {unit: rad/s}
  gyro: {unit: rad/s}
parameters:
  r_l: {value: 0.05, unit: m, scale: 0.05}
  r_r: {value: 0.05, unit: m, scale: 0.05}
  b: {value: 0.3, unit: m, scale: 0.3}
  k: {value: 1.0, scale: 1.0}
constraints:
  g: {expr: (r_r*w_r - r_l*w_l)/b - k*gyro, unit: rad/s}
datasets:
  calibration: {path: data.csv}
"""

CURVE = """\
problem: curve
columns:
  w: {unit: rad/s}
  gyro: {unit: rad/s}
parameters:
  a: {value: 0.5, scale: 1.0}
  c: {value: 1.0, scale: 1.0}
constraints:
  g: {expr: sin(a)*w - c*gyro, unit: rad/s}
datasets:
  calibration: {path: data.csv}
"""


def _drive_data(n: int = 300, noise: float = 1e-3, seed: int = 1) -> dict[str, np.ndarray]:
    """A differential drive: r_l 0.049, r_r 0.051 m, b 0.31 m, k 1.02."""
    rng = np.random.default_rng(seed)
    v, omega = rng.uniform(0, 0.5, n), rng.uniform(-1, 1, n)
    w_l = (v - omega * 0.31 / 2) / 0.049 + noise * rng.standard_normal(n)
    w_r = (v + omega * 0.31 / 2) / 0.051 + noise * rng.standard_normal(n)
    gyro = omega / 1.02 + noise * rng.standard_normal(n)
    return {"w_l": w_l, "w_r": w_r, "gyro": gyro, "w": w_l}


def _problem(folder: Path, text: str, extra: str = "") -> Path:
    data = _drive_data()
    names = ["w_l", "w_r", "gyro", "w"]
    np.savetxt(folder / "data.csv", np.column_stack([data[c] for c in names]),
               delimiter=",", header=",".join(names), comments="")
    path = folder / "problem.yaml"
    path.write_text(text + extra)
    return path


def test_a_scale_of_opposite_powers_is_named_a_scale(tmp_path, capsys) -> None:
    path = _problem(tmp_path, SIGNS)
    result = symcal.solve(path)
    (gauge,) = result.stages[0].gauges.gauges
    assert (gauge.kind, gauge.parameters, gauge.degree) == ("scale", ("b", "k"), 1.0)
    assert gauge.weights == {"b": -1.0, "k": 1.0}
    assert "homogeneous of degree 1 in b, k (powers b: -1, k: 1)" in gauge.text
    assert "the trivial point where k is zero and b grows without bound" in gauge.text
    # it is one, checked with numpy: g(b / lam, lam k) = lam g(b, k)
    data = _drive_data()

    def g(b: float, k: float) -> np.ndarray:
        return 0.2 * data["w"] / b - k * data["gyro"]

    np.testing.assert_allclose(g(0.3 / 2.5, 2.5 * 1.1), 2.5 * g(0.3, 1.1), rtol=1e-12)
    # the solve slides towards the trivial point: a failure, never a success
    assert not result.success
    assert main(["solve", str(path)]) == 1
    capsys.readouterr()


def test_gauges_that_share_parameters_are_one_fix_set(tmp_path) -> None:
    """Two scales share the wheel radii: degree 1 in (r_l, r_r, k) and degree 0 in
    (r_l, r_r, b).  Fixing r_l satisfies 'fix one of' in each, and is not enough: they
    are one fix set of 2, with an example that fixes both."""
    path = _problem(tmp_path, DRIVE)
    free = symcal.solve(path)
    scale, invariance = free.stages[0].gauges.gauges
    assert (scale.kind, scale.degree, scale.weights) == (
        "scale", 1.0, {"r_l": 1.0, "r_r": 1.0, "k": 1.0})
    assert (invariance.kind, invariance.degree, invariance.weights) == (
        "scale", 0.0, {"r_l": 1.0, "r_r": 1.0, "b": 1.0})
    fix = ("fix 2 of r_l, r_r, k, b: e.g. k and b (these 2 gauges share r_l, r_r, so one "
           "fix of each is not enough)")
    assert scale.fix == invariance.fix == fix
    assert scale.text.endswith(fix) and invariance.text.endswith(fix)
    # unfixed: the radii and k slide to zero, a failed solve (it was 'exact fit', exit 0)
    assert not free.success
    assert free.stages[0].message.startswith(
        "failed: the solve collapsed onto the trivial point of a gauge: r_l, r_r, k all "
        "went to zero")
    # one shared parameter is not enough; the example is
    one = symcal.solve(_fixed(tmp_path, ["r_l"]))
    assert one.identifiability.rank == one.identifiability.n_free - 1
    both = symcal.solve(_fixed(tmp_path, ["k", "b"]))
    assert both.success
    assert both.identifiability.rank == both.identifiability.n_free == 2
    assert not both.stages[0].gauges.gauges
    # with b = 0.3 and k = 1 (truth 0.31, 1.02) each radius is found as r 0.3 / (0.31 1.02)
    assert both.params["r_l"].value == pytest.approx(0.049 * 0.3 / 0.31 / 1.02, rel=1e-3)


def _fixed(folder: Path, names: list[str]) -> Path:
    """The drive problem with ``names`` fixed at their initial values."""
    text = DRIVE.replace("problem: drive", f"problem: drive_{'_'.join(names)}")
    for n in names:
        text = text.replace(f"  {n}: {{value:", f"  {n}: {{fixed: true, value:")
    path = folder / f"fixed_{'_'.join(names)}.yaml"
    path.write_text(text)
    return path


def test_a_collapse_is_a_failed_solve_whatever_the_gauge_is_called(tmp_path, capsys) -> None:
    """sin(a) w - c gyro: scaling sin(a) and c together is a gauge, but no power law in
    a; the solve slides to a = c = 0, where the constraint vanishes whatever the data."""
    path = _problem(tmp_path, CURVE)
    result = symcal.solve(path)
    assert not result.success
    message = result.stages[0].message
    assert message.startswith("failed: the solve collapsed onto a trivial point, where the "
                              "constraints vanish whatever the data")
    assert ": a, c went to zero; fix one of a, c" in message
    assert main(["solve", str(path)]) == 1
    capsys.readouterr()


def test_an_exact_fit_is_no_collapse(tmp_path) -> None:
    """Noiseless data of the fixed drive: an exact fit, and a success."""
    data = _drive_data(noise=0.0)
    names = ["w_l", "w_r", "gyro", "w"]
    np.savetxt(tmp_path / "data.csv", np.column_stack([data[c] for c in names]),
               delimiter=",", header=",".join(names), comments="", fmt="%.17g")
    result = symcal.solve(_fixed(tmp_path, ["k", "b"]))
    assert result.success, result.stages[0].message
    assert result.params["r_r"].value == pytest.approx(0.051 * 0.3 / 0.31 / 1.02, rel=1e-9)
