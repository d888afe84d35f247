"""Gauges found before the solve (symcal/analysis/gauges.py) on small problems whose
symmetries are known by construction, and the rank decision that counts them
(symcal/base/linalg.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import symcal
from symcal.base.linalg import known_null_svd


def _problem(tmp: Path, constraint: str, parameters: dict[str, float], y,
             noise: float = 1e-3) -> Path:
    x = np.linspace(0.5, 3.0, 60)
    rng = np.random.default_rng(0)
    table = np.column_stack([x, y(x) + noise * rng.standard_normal(x.size)])
    np.savetxt(tmp / "d.csv", table, delimiter=",", header="x,y", comments="")
    params = "\n".join(f"  {n}: {{value: {v}, scale: 1}}" for n, v in parameters.items())
    path = tmp / "p.yaml"
    path.write_text(f"problem: p\ncolumns: {{x: {{}}, y: {{}}}}\nparameters:\n{params}\n"
                    f"constraints:\n  r: {constraint}\n"
                    "datasets:\n  calibration: {path: d.csv}\n")
    return path


def _gauges(path: Path):
    result = symcal.solve(path)
    return result, result.stages[0].gauges.gauges


def test_parameters_that_enter_only_through_a_sum_are_an_offset(tmp_path) -> None:
    path = _problem(tmp_path, "(a + b)*x + c - y", {"a": 1, "b": 0.5, "c": 0},
                    lambda x: 2 * x + 1)
    result, gauges = _gauges(path)
    (offset,) = gauges
    assert offset.kind == "offset" and offset.parameters == ("a", "b")
    assert [c.text for c in offset.directions] == ["a - b"]
    assert offset.fix == "fix one of a, b"
    # the identifiability analysis names the same direction, and the sum is determined
    assert [c.text for c in result.identifiability.null_space] == ["a - b"]
    assert result.params["a"].value + result.params["b"].value == pytest.approx(2.0, abs=1e-3)


def test_a_weighted_homogeneity_is_a_scale_with_its_powers(tmp_path) -> None:
    # g(λ·a, √λ·b) = λ·g: homogeneous of degree 1 with powers a: 1, b: 0.5
    _, gauges = _gauges(_problem(tmp_path, "a*x - b*b*y", {"a": 1.0, "b": 1.2},
                                 lambda x: 0.7 * x))
    (scale,) = gauges
    assert scale.kind == "scale" and scale.parameters == ("a", "b")
    assert scale.weights == {"a": 1.0, "b": 0.5} and scale.degree == 1.0
    assert "(powers a: 1, b: 0.5)" in scale.text
    assert scale.fix == "fix one of a, b or give one of them a known value"


def test_an_identifiable_model_has_no_gauge(tmp_path) -> None:
    result, gauges = _gauges(_problem(tmp_path, "y - a*exp(-b*x)", {"a": 1.0, "b": 0.5},
                                      lambda x: 2 * np.exp(-0.7 * x)))
    assert gauges == ()
    assert result.success and result.identifiability.rank == 2


def test_known_null_directions_are_counted_whatever_the_noise() -> None:
    rng = np.random.default_rng(1)
    a = rng.standard_normal((40, 5))
    v = np.array([1.0, -2.0, 0.0, 0.5, 0.0])
    a = a - np.outer(a @ v, v) / (v @ v)
    noisy = a + 1e-6 * rng.standard_normal(a.shape)   # v no longer exactly null
    s, _, rank = known_null_svd(noisy, 40, np.zeros((0, 5)))
    assert rank == 5                                   # the plain decision misses it
    s, vt, rank = known_null_svd(noisy, 40, v[None, :])
    assert rank == 4
    null = vt[rank:][0]
    assert abs(null @ v) / np.linalg.norm(v) == pytest.approx(1.0, abs=1e-12)
    # the rest of the spectrum is the projected matrix's, as numpy computes it
    q = v / np.linalg.norm(v)
    expected = np.linalg.svd(noisy - np.outer(noisy @ q, q), compute_uv=False)
    np.testing.assert_allclose(s[:4], expected[:4], rtol=1e-12)


@pytest.mark.parametrize("line", [lambda x: 2 * x + 1, lambda x: 0 * x])
def test_an_exact_fit_is_no_gauge(tmp_path, line) -> None:
    """Noise-free readings that a linear model fits exactly satisfy J·(θ - θ*) = g at every
    point (and, when θ* = 0, g is even homogeneous in θ): a coincidence of these data,
    not a symmetry of the model, so nothing is named and the solve succeeds."""
    result, gauges = _gauges(_problem(tmp_path, "y - a*x - b", {"a": 1.0, "b": 0.5}, line,
                                      noise=0.0))
    assert gauges == ()
    assert result.success and result.identifiability.rank == 2
    assert result.params["a"].value == pytest.approx(line(1.0) - line(0.0), abs=1e-9)
