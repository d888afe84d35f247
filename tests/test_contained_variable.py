"""A residual that is a variable whole, up to its sign and a constant (a magnetometer's
``g_B = norm - B0``), is not said to vary with it: binned along ``norm`` it did so
trivially ("varies with norm: η² = 0.96", "150 % of its excess along norm"), and the
three places of "what is left" went to it, so that the time the effect followed was
never named."""

from __future__ import annotations

import numpy as np
from conftest import magnetometer_gain_time

import symcal
from symcal.revise.diagnose import _contains


def test_a_residual_is_not_binned_along_itself(tmp_path) -> None:
    diag = symcal.diagnose(symcal.solve(magnetometer_gain_time(tmp_path)))
    view = next(v for v in diag.residuals if v.dataset == "calibration")
    assert view.left, "the residual is above its floor: something is left"
    assert all("norm" not in a.variables for a in view.left), view.left
    assert all(b.variable != "norm" for b in view.binned), \
        [b.variable for b in view.binned]
    assert any("t" in a.variables for a in view.left), view.left


def test_contained_up_to_sign_and_constant() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(50.0, 3.0, 500)
    assert _contains(x - 48.6, x) and _contains(48.6 - x, x)
    assert not _contains(x - 48.6 + rng.normal(0, 1e-3, 500), x)
    assert not _contains(2 * x, x) and not _contains(x, np.full(500, 2.0))
