"""The closed-form path: linear detection, agreement with numpy, null space, recovery."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, F, basis, courier_data

import symcal
from symcal.base.errors import SolveError
from symcal.data.dataset import make_dataset
from symcal.solvers.objective import Objective

PROBLEM = ROOT / "problems" / "platen_self_calibration.yaml"
NOISE = 0.5e-3


def _data(k: np.ndarray, n: int = 1000, seed: int = 3,
          flyby: bool = True) -> dict[str, symcal.Dataset]:
    data = {"calibration": make_dataset("calibration", "test",
                                        courier_data(n, k, NOISE, seed), [])}
    if flyby:
        data["flyby"] = make_dataset("flyby", "test", courier_data(200, k, NOISE, seed + 1), [])
    return data


def _numpy_design(cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A and b of eq. (7), assembled with numpy alone."""
    a = np.hstack([basis(cols["p1"]), -basis(cols["p2"]), -basis(cols["p3"]),
                   basis(cols["p4"])])
    b = (cols["p1"] - cols["p3"]) - (cols["p2"] - cols["p4"])
    return a, b


def _true_k() -> np.ndarray:
    rng = np.random.default_rng(42)
    return rng.normal(0, 0.004, (4, 9)) / np.array([1, 1, 1, 2, 2, 4, 4, 6, 6])


@pytest.fixture(scope="module")
def solved() -> tuple[symcal.Result, dict, np.ndarray]:
    """Solved with the paper's equal weights (the eq. 7 least squares numpy solves)."""
    k = _true_k()
    data = _data(k)
    problem = symcal.load_problem(PROBLEM).with_weighting("equal")
    return symcal.solve(problem, data), data, k


def _slopes(cols: dict[str, np.ndarray], k: np.ndarray) -> np.ndarray:
    """∂g_p/∂p_i (N × 4) for eq. (3) coefficients ``k`` (4 × 9), with numpy alone."""
    out = []
    for i, sign in enumerate((1, -1, -1, 1)):
        p = cols[f"p{i + 1}"]
        d = np.zeros_like(p)
        for m, h in enumerate((1, 2, 4, 6)):
            d += h * F * (k[i, 1 + 2 * m] * np.cos(h * F * p) - k[i, 2 + 2 * m] * np.sin(h * F * p))
        out.append(sign * (1 + d))
    return np.column_stack(out)


def test_propagated_weighting_equals_numpy_weighted_least_squares() -> None:
    """The default weighting: each row weighted by the inverse of g_p's variance
    propagated from the 0.503 µm declared noise of its four readings.  The weights are
    taken at the start (k = 0: all equal, the plain least squares) and again at that
    estimate; numpy does the same with its own derivatives of eq. (3)."""
    k = _true_k()
    data = _data(k)
    result = symcal.solve(symcal.load_problem(PROBLEM), data)
    assert result.problem.weighting == "propagated" and result.method == "linear"
    cols = {c: np.asarray(v) for c, v in data["calibration"].columns.items()}
    a, b = _numpy_design(cols)
    first = np.linalg.lstsq(a, -b, rcond=None)[0].reshape(4, 9)
    var = 0.503e-3**2 * np.sum(_slopes(cols, first) ** 2, axis=1)
    w = 1 / np.sqrt(var)
    k_np = np.linalg.lstsq(a * w[:, None], -b * w, rcond=None)[0]
    est = np.array([result.params[f"s{i}.k{j}"].value for i in range(1, 5) for j in range(9)])
    np.testing.assert_allclose(est, k_np, rtol=0, atol=1e-11)
    rss = float(np.sum(((a @ k_np + b) * w) ** 2))
    cov = rss / (a.shape[0] - 33) * np.linalg.pinv((a * w[:, None]).T @ (a * w[:, None]),
                                                   rcond=1e-10)
    for i, name in enumerate(f"s{i}.k{j}" for i in range(1, 5) for j in range(9)):
        if not name.endswith("k0"):
            assert result.uncertainty.se[name] == pytest.approx(np.sqrt(cov[i, i]),
                                                                rel=1e-6)
    # χ²/dof of g_p is the weighted RSS over its degrees of freedom (the test's weights
    # are those at the final estimate, the solve's at the one before: 5e-6 apart here)
    assert result.stat("g_p").chi2_dof == pytest.approx(rss / (1000 - 33), rel=1e-4)


def test_method_is_closed_form(solved) -> None:
    result, _, _ = solved
    assert result.method == "linear"
    assert [st.iterations for st in result.stages] == [0]
    assert result.success


def test_closed_form_equals_numpy_lstsq(solved) -> None:
    result, data, _ = solved
    cols = {k: np.asarray(v) for k, v in data["calibration"].columns.items()}
    a, b = _numpy_design(cols)
    # segment order in theta is s1, s2, s3, s4; _numpy_design follows it
    k_np = np.linalg.lstsq(a, -b, rcond=None)[0]
    est = np.array([result.params[f"s{i}.k{j}"].value for i in range(1, 5) for j in range(9)])
    np.testing.assert_allclose(est, k_np, rtol=0, atol=1e-11)


def test_rank_and_condition_equal_numpy(solved) -> None:
    result, data, _ = solved
    a, _ = _numpy_design({k: np.asarray(v) for k, v in data["calibration"].columns.items()})
    sv = np.linalg.svd(a, compute_uv=False)
    rank = int(np.sum(sv > sv[0] * 1e-10))
    assert result.identifiability.rank == rank == 33
    assert result.identifiability.condition_number == pytest.approx(sv[0] / sv[rank - 1],
                                                                    rel=1e-9)


def test_null_space_in_parameter_names(solved) -> None:
    ident = solved[0].identifiability
    assert ident.deficiency == 3
    assert [c.text for c in ident.null_space] == [
        "s1.k0 - s4.k0", "s2.k0 + s4.k0", "s3.k0 + s4.k0"]
    assert [c.text for c in ident.identifiable_combinations] == [
        "s1.k0 - s2.k0 - s3.k0 + s4.k0"]


def test_standard_errors_equal_numpy(solved) -> None:
    """Equal weights on rows whose declared noise differs (g_p's variance follows each
    reading's slope): the sandwich ``σ̂₀² A⁺ (Σ a_iᵀ var_i a_i) A⁺``, ``σ̂₀²`` the residual
    sum of squares over ``Σ var_i − tr(A⁺B)``, with numpy alone; the pooled
    ``s² A⁺`` differs from it by more than the tolerance."""
    result, data, _ = solved
    cols = {k: np.asarray(v) for k, v in data["calibration"].columns.items()}
    a, b = _numpy_design(cols)
    k_np = np.linalg.lstsq(a, -b, rcond=None)[0]
    rss = float(np.sum((a @ k_np + b) ** 2))
    var = 0.503e-3**2 * np.sum(_slopes(cols, k_np.reshape(4, 9)) ** 2, axis=1)
    a_pinv = np.linalg.pinv(a.T @ a, rcond=1e-10)
    meat = a.T @ (var[:, None] * a)
    factor = rss / (np.sum(var) - np.trace(a_pinv @ meat))
    cov = factor * a_pinv @ meat @ a_pinv
    pooled = rss / (a.shape[0] - 33) * a_pinv
    assert np.max(np.abs(np.sqrt(np.diag(pooled)[1:9] / np.diag(cov)[1:9]) - 1)) > 1e-3
    assert any("the sandwich of the fit's weights" in n for n in result.stages[-1].notes)
    names = [f"s{i}.k{j}" for i in range(1, 5) for j in range(9)]
    for i, name in enumerate(names):
        p = next(q for q in result.params.values() if q.name == name)
        if name.endswith("k0"):
            assert p.se is None and "combination" in p.se_reason
        else:
            assert p.se == pytest.approx(np.sqrt(cov[i, i]), rel=1e-6)
    c = np.zeros(36)
    c[[0, 27]], c[[9, 18]] = 1, -1
    combo = result.identifiability.identifiable_combinations[0]
    assert combo.se == pytest.approx(np.sqrt(c @ cov @ c), rel=1e-6)


def test_recovery_within_four_standard_errors(solved) -> None:
    result, _, k = solved
    for i in range(4):
        for j in range(1, 9):
            p = next(q for q in result.params.values() if q.name == f"s{i + 1}.k{j}")
            assert abs(p.value - k[i, j]) < 4 * p.se, p.name
    combo = result.identifiability.identifiable_combinations[0]
    true = k[0, 0] - k[1, 0] - k[2, 0] + k[3, 0]
    assert abs(combo.value - true) < 4 * combo.se


def test_calibrated_residual_at_noise_floor(solved) -> None:
    result, _, _ = solved
    floor = 2 * NOISE * np.sqrt((1000 - 33) / 1000)
    assert result.stat("g_p", unit="mm").after.rms == pytest.approx(floor, rel=0.1)
    assert result.stat("g_p", unit="mm").before.rms > 5 * floor


def _variant(tmp_path: Path, extra: str, constraint: str) -> Path:
    model = (ROOT / "models" / "platen_segment.yaml").as_posix()
    text = textwrap.dedent(f"""\
        problem: variant
        constants:
          per_mm: {{value: 1, unit: 1/mm}}   # keeps a product of two lengths a length
        instances:
          s1: {{model: {model}, inputs: {{p: p1}}{extra}}}
          s2: {{model: {model}, inputs: {{p: p2}}}}
          s3: {{model: {model}, inputs: {{p: p3}}}}
          s4: {{model: {model}, inputs: {{p: p4}}}}
        constraints:
          g: {constraint}
        datasets:
          calibration: {{path: data.csv}}
        columns: courier
        """)
    path = tmp_path / "variant.yaml"
    path.write_text(text)
    return path


BASE_G = "(s1.p_hat - s3.p_hat) - (s2.p_hat - s4.p_hat)"


def test_nonlinear_constraint_goes_to_lm(tmp_path: Path, true_k) -> None:
    path = _variant(tmp_path, "", BASE_G + " + s1.k1*s2.k1*per_mm")
    problem = symcal.load_problem(path)
    free = np.ones(len(problem.parameters), dtype=bool)
    assert Objective(problem, ("g",), free).nonlinear() == ["g"]
    result = symcal.solve(problem, _data(true_k, 300, flyby=False))
    assert result.method == "lm" and result.success
    with pytest.raises(SolveError) as err:
        symcal.solve(problem, _data(true_k, 300, flyby=False),
                     symcal.SolveOptions(method="linear"))
    assert str(err.value) == ("stage 'calibration': method 'linear' was asked for, but "
                              "constraint(s) g are not linear in its free parameters")


def test_linear_in_free_parameters_when_partner_fixed(tmp_path: Path, true_k) -> None:
    path = _variant(tmp_path, ", parameters: {k1: {value: 0.002, fixed: true}}",
                    BASE_G + " + s1.k1*s2.k1*per_mm")
    result = symcal.solve(symcal.load_problem(path), _data(true_k, 300, flyby=False))
    assert result.method == "linear"
    assert result.params["s1.k1"].value == 0.002
    assert result.identifiability.n_free == 35


def test_unidentifiable_directions_keep_initial_values(tmp_path: Path, true_k) -> None:
    path = _variant(tmp_path, ", parameters: {k0: {value: 0.003}}", BASE_G)
    result = symcal.solve(symcal.load_problem(path), _data(true_k, 300, flyby=False))
    step = np.array([result.params[f"s{i}.k0"].value for i in range(1, 5)]) - [0.003, 0, 0, 0]
    # null directions of the offsets: everything orthogonal to (1, -1, -1, 1)
    null = np.array([[1, 0, 0, -1], [0, 1, 0, 1], [0, 0, 1, 1]], dtype=float)
    q, _ = np.linalg.qr(null.T)
    assert np.abs(q.T @ step).max() < 1e-12
