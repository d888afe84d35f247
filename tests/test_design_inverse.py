"""The design optimiser inverts per-observation information matrices whose pivots are
small in absolute terms (a magnetometer's scale factor beside a term linear in its
reading: eigenvalues 2e-14 to 8e-4); CasADi's default QR refused them ('Evaluation
failed', an internal error from ``symcal design --optimize``)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from symcal.experiment.optimize import _inverse


def _information(seed: int) -> np.ndarray:
    """Unit-diagonal information with two nearly aliased parameters (eigenvalues 2e-6 to
    about 2), in parameters whose scales span seven decades."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(7, 7)))
    core = q @ np.diag([2.4e-6, 0.67, 0.91, 0.99, 1.0, 1.05, 2.38]) @ q.T
    root = np.sqrt(np.diag(core))
    core = core / np.outer(root, root)
    scale = np.diag(10.0 ** rng.uniform(-7, -1.5, 7))
    return scale @ core @ scale


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_inverse_of_a_badly_scaled_information_matrix(seed: int) -> None:
    gram = _information(seed)
    x = ca.MX.sym("x", 7, 7)
    with pytest.raises(RuntimeError, match="Evaluation failed"):
        ca.Function("f", [x], [ca.solve(x, ca.DM.eye(7))])(gram)
    got = np.array(ca.Function("f", [x], [_inverse(x, 7)])(gram))
    want = np.linalg.inv(gram)
    assert np.allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
