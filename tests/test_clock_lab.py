"""A new user's clock lab (``tests/data/clock``): two crystal oscillators against a GNSS
PPS, fractional frequencies in ns/s, aging per hour, a parabolic temperature curve.

- **A product with time is written about the run's temperature.**  A temperature
  coefficient growing with age, ``0.1 ns/s/°C/h·(T - 25 °C)·t``, was written
  ``prod_T_t*T*t``: the aging rate became the rate at 0 °C, 7-11 SE from the physical
  rate.  Time stays uncentred; the temperature is centred where the aging rate absorbs
  the part linear in time.
- **Coefficients in the user's ratio.**  The output in ns/s: a drift was written in
  ``1/h`` (``2.5e-10``); it is now ``ns/s/h``.
"""

from __future__ import annotations

import pytest
from conftest import ROOT, simulated, with_effect

import symcal
from symcal.revise.effects import per
from symcal.simulation import truth

CLOCK = ROOT / "tests" / "data" / "clock"


def test_a_ratio_the_user_reads_in_is_kept_in_a_coefficients_unit() -> None:
    assert per("ns/s", ("hour", 1)) == "ns/s/h"
    assert per("ns/s", ("delta_degC", 1), ("hour", 1)) == "ns/s/Δ°C/h"
    assert per("ns/s") == "ns/s"
    assert per("ns/s", ("ns/s", 1)) == ""          # a plain ratio stays plain
    assert per("rad", ("rad", 1), ("K", 1)) == "1/K"   # an angle over an angle cancels
    assert per("mm", ("K", 1)) == "mm/K"


@pytest.mark.slow
def test_a_temperature_coefficient_growing_with_age_keeps_the_aging_rate(tmp_path) -> None:
    scenario = with_effect(CLOCK, "tc_aging")
    data = simulated(scenario, 3)
    done = symcal.improve(CLOCK / "problem.yaml", tmp_path / "out", data, max_rounds=3)
    assert done.verified
    assert [r.added for r in done.rounds[1:]] == ["A.y += the product of T and t"]
    model = next((tmp_path / "out" / "models").glob("*prod_T_t*.yaml")).read_text()
    assert "y: base.y + prod_T_t*(T - c_prod_T_t)*t" in model
    assert "prod_T_t: {value: 0, unit: ns/s/Δ°C/h," in model
    final = symcal.solve(done.final_problem, data)
    true = truth(scenario)["parameters"]
    for name in ("A.a", "A.c", "A.T_turn", "B.a", "B.T_turn"):
        p = final.params[name]
        assert abs(p.value - true[name]) < 3 * p.se, (name, p.value, true[name], p.se)
    coef = final.params["A.prod_T_t"]
    assert abs(coef.value - 0.1) < 3 * coef.se


def test_a_pair_the_residual_is_written_with_is_not_what_is_left() -> None:
    """``g = n/f0 − 1 − y`` binned along (n, y) "explains" itself: 10970 % of the
    excess "along (nA, A.y) together" in the clock lab's verdict; such a pair is left out.
    (Pairs with the count itself still rank high: binned along a noisy reading, a
    residual's own noise sorts with it.)"""
    import numpy as np

    from symcal.analysis.residuals import Variable, what_is_left

    rng = np.random.default_rng(4)
    n = 4000
    temp = rng.uniform(17, 33, n)
    y = 1e-7 * rng.normal(size=n)
    t = np.linspace(0, 24, n)
    step = 2e-8 * (temp > 25) * (t > 12)             # what the count carries unmodelled
    count = 1e7 * (1 + y + step + 35e-9 * rng.normal(size=n))
    r = count / 1e7 - 1 - y
    r -= r.mean()
    found = what_is_left(r, [Variable("nA", count), Variable("A.y", y), Variable("T", temp),
                             Variable("t", t)], floor_variance=(35e-9) ** 2)
    pairs = [set(f.variables) for f in found if len(f.variables) == 2]
    assert pairs and {"nA", "A.y"} not in pairs


def test_ppb_is_a_unit_and_ppt_is_refused() -> None:
    from symcal.base.units import UnitError, parse_unit, size

    assert size("ppb") == pytest.approx(1e-9) and size("ppb/h") == pytest.approx(1e-9 / 3600)
    with pytest.raises(UnitError, match="'ppt' is ambiguous .* pint reads it as a picopint"):
        parse_unit("ppt/K")
