"""Units end to end in the Python API (issue 24 item 3): every number Result.value and
Result.stat return is in the unit they state; offset units are refused with the reason
and the alternatives."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.base.errors import SymcalError

TRIAD = ROOT / "examples" / "accelerometer_triad" / "problem_fixed.yaml"


@pytest.fixture(scope="module")
def triad() -> symcal.Result:
    return symcal.solve(TRIAD)


def _norm(result: symcal.Result, dataset: str) -> np.ndarray:
    """The calibrated specific force's magnitude in m/s^2, by numpy from the readings."""
    p = {n: q.value for n, q in result.params.items()}
    a = result.data[dataset].columns
    u = [p[f"acc.k_{c}"] * (a[f"a{c}"] - p[f"acc.b_{c}"]) for c in "xyz"]
    f = [u[0] - p["acc.m_yz"] * u[1] + p["acc.m_zy"] * u[2],
         p["acc.m_xz"] * u[0] + u[1] - p["acc.m_zx"] * u[2],
         -p["acc.m_xy"] * u[0] + p["acc.m_yx"] * u[1] + u[2]]
    return np.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)


def test_values_are_in_the_unit_each_quantity_declares(triad) -> None:
    norm = _norm(triad, "validation")
    assert triad.unit_of("norm") == "m/s**2" and triad.unit_of("g_n") == "mm/s**2"
    np.testing.assert_allclose(triad.value("norm", "validation"), norm, rtol=1e-13)
    np.testing.assert_allclose(triad.value("g_n", "validation"), (norm - 9.8105) * 1e3,
                               rtol=1e-9, atol=1e-9)
    # a sensor signal, in its model's unit; another unit, or the internal one, on request
    assert triad.unit_of("acc.fz") == "m/s**2"
    fz = triad.value("acc.fz", "validation")
    np.testing.assert_allclose(triad.value("acc.fz", "validation", unit="(internal)"),
                               fz * 1e3, rtol=1e-13)
    np.testing.assert_allclose(triad.value("acc.fz", "validation", unit="cm/s**2"),
                               fz * 100, rtol=1e-13)
    with pytest.raises(ValueError, match="'s' is not a unit of 'norm', which is in 'm/s"):
        triad.value("norm", unit="s")


def test_statistics_are_in_the_unit_they_state(triad) -> None:
    g = _norm(triad, "validation") - 9.8105          # m/s^2
    stat = triad.stat("g_n", "validation")
    assert stat.unit == "mm/s**2"
    assert stat.after.std == pytest.approx(np.std(g) * 1e3, rel=1e-9)
    assert stat.after.rms == pytest.approx(np.sqrt(np.mean(g**2)) * 1e3, rel=1e-9)
    assert stat.shown("after") == stat.after
    metres = triad.stat("g_n", "validation", unit="m/s**2")
    assert metres.unit == "m/s**2"
    assert metres.after.std == pytest.approx(np.std(g), rel=1e-9)
    internal = triad.stat("g_n", "validation", unit="(internal)")
    assert internal.unit == "mm/s^2" and internal.after.std == pytest.approx(stat.after.std)
    # the report's table says the same as the API
    assert f"{stat.after.std:.4g}" in symcal.text_report(triad)


def test_saved_and_loaded_results_give_the_same_numbers(triad, tmp_path) -> None:
    path = triad.save(tmp_path / "result.json")
    again = symcal.Result.load(path)
    assert again.stat("g_n", "validation") == triad.stat("g_n", "validation")
    np.testing.assert_allclose(again.value("norm", "validation"),
                               triad.value("norm", "validation"), rtol=0, atol=0)


def test_an_offset_unit_is_refused_with_the_reason_and_the_alternatives(tmp_path) -> None:
    model = tmp_path / "thermometer.yaml"
    model.write_text("model: thermometer\ninputs:\n  v: {unit: V}\nparameters:\n"
                     "  t0: {value: 20, unit: degC}\noutputs:\n  temp: {expr: v + t0}\n")
    problem = tmp_path / "p.yaml"
    problem.write_text("problem: p\ncolumns: {v: {unit: V}}\ninstances:\n"
                       "  th: {model: thermometer.yaml, inputs: {v: v}}\n"
                       "constraints: {g: th.temp}\ndatasets: {calibration: {path: d.csv}}\n")
    with pytest.raises(SymcalError) as err:
        symcal.load_problem(problem)
    assert str(err.value).endswith(
        "parameters.t0.unit: unit 'degC' has an offset (0 degC is 273.15 K): symcal converts "
        "units by scaling alone, which cannot carry an offset; use 'kelvin' for a "
        "temperature, or 'delta_degC' for a temperature difference; units are pint's (mm, "
        "um, m, rad, mrad, deg, s, mm/s, ...)")
