"""Outliers and the global test where each row's noise differs (the propagated weighting).

The thermistor bath of tests/acceptance/thermistor_bath: 0.5 ohm of ohmmeter noise is 1 to
25 mK of the constraint g_T across the range, so one robust spread of g_T for all rows
flagged the noisiest rows of clean data as outliers (87 of 1200 on seed 1000).  A row's
residual is now tested over its own propagated standard deviation (the w-test of an
adjustment).  The calibration χ²/dof is checked against an independent numpy
computation of Σ g²/var_i/(N - 3) at symcal's estimate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.analysis.outliers import MAD_TO_SIGMA, THRESHOLD, find_outliers
from symcal.data.dataset import make_dataset
from symcal.data.loading import needed_columns
from symcal.simulation import load_scenario, simulate_run

BATH = ROOT / "tests/acceptance/thermistor_bath"
SIGMA_R = 0.5     # ohm, the scenario's and the models' ohmmeter noise
LEAD = 0.5        # ohm, the models' r_lead
TH1 = (298.15, 3950.0, 1.2e-7, 10000.0)     # the fixed reference part: T0, B, c3, R0
R0_2 = 5000.0


def _temperature(r: np.ndarray, t0: float, beta: float, c3: float, r0: float) -> np.ndarray:
    x = np.log((r - LEAD) / r0)
    return 1.0 / (1.0 / t0 + x / beta + c3 * x**3)


def _slope(r: np.ndarray, t0: float, beta: float, c3: float, r0: float) -> np.ndarray:
    """dT/dR of the Steinhart-Hart law, by hand."""
    x = np.log((r - LEAD) / r0)
    return -_temperature(r, t0, beta, c3, r0) ** 2 * (1.0 / beta + 3.0 * c3 * x**2) / (r - LEAD)


def _numpy_g(cols: dict[str, np.ndarray], th2: tuple[float, float, float]
             ) -> tuple[np.ndarray, np.ndarray]:
    """g_T (K) and its propagated standard deviation (K) of each row, numpy alone."""
    p2 = (*th2, R0_2)
    g = _temperature(cols["R1"], *TH1) - _temperature(cols["R2"], *p2)
    sd = SIGMA_R * np.hypot(_slope(cols["R1"], *TH1), _slope(cols["R2"], *p2))
    return g, sd


def _solve(cols: dict[str, np.ndarray]) -> symcal.Result:
    problem = symcal.load_problem(BATH / "problem.yaml")
    assert problem.weighting == "propagated"
    data = make_dataset("calibration", "memory", cols, needed_columns(problem))
    return symcal.solve(problem, {"calibration": data})


def _th2(result: symcal.Result) -> tuple[float, float, float]:
    values = {p["name"]: p["value"] for p in result.to_dict()["parameters"]}
    return values["th2.T0"], values["th2.beta"], values["th2.c3"]


def _calibration(seed: int) -> dict[str, np.ndarray]:
    return simulate_run(load_scenario(BATH / "scenario.yaml"), "calibration", seed=seed)


def _numpy_z(g: np.ndarray, sd: np.ndarray) -> np.ndarray:
    u = g / sd
    centre = np.median(u)
    return np.abs(u - centre) / (MAD_TO_SIGMA * np.median(np.abs(u - centre)))


def test_standardized_outliers_against_numpy() -> None:
    """Rows whose noise runs from 1 to 25: one spread for all flags the noisiest rows;
    over each row's own standard deviation, only the planted outliers (8 of their own
    σ on quiet rows, small beside the noisy rows' residuals) are found, their whitened
    residuals as numpy computes them."""
    rng = np.random.default_rng(3)
    n = 3000
    sd = np.geomspace(1.0, 25.0, n)
    g = sd * rng.standard_normal(n)
    planted = np.array([10, 200, 400])
    g[planted] = 8.0 * sd[planted]
    one = find_outliers("calibration", ("r",), ("mK",), np.array([1.0]), g[:, None], None,
                        "squared")
    assert one.count > 50                                  # the false alarm of one spread
    assert not set(planted) & {o.row for o in one.listed}
    found = find_outliers("calibration", ("r",), ("mK",), np.array([1.0]), g[:, None], None,
                          "squared", sd=sd[:, None])
    z = _numpy_z(g, sd)
    assert found.count == int(np.sum(z > THRESHOLD)) == 3
    assert sorted(o.row for o in found.listed) == planted.tolist()
    for o in found.listed:
        assert o.whitened == pytest.approx(z[o.row], rel=1e-12)
        assert o.residual == pytest.approx(g[o.row], rel=1e-12)    # the residual itself
    u = g / sd
    assert found.standardized_std is not None
    assert found.standardized_std["r"] == pytest.approx(
        MAD_TO_SIGMA * np.median(np.abs(u - np.median(u))), rel=1e-12)
    assert found.robust_std["r"] == pytest.approx(one.robust_std["r"], rel=1e-12)
    assert found.share == pytest.approx(np.sum(u[planted] ** 2) / np.sum(u**2), rel=1e-12)
    again = type(found).from_dict(found.to_dict())
    assert again == found


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1000, 1001, 1002])
def test_clean_thermistor_data_have_no_outliers_and_the_numpy_chi2(seed: int) -> None:
    """Clean bath data: no outliers (seed 1000 had 87 under one spread), the standardized
    residuals' robust spread near 1, and symcal's calibration χ² equal to numpy's
    Σ g²/var_i at symcal's estimate (the noise propagated at the readings), its χ²/dof
    within 1/(N - 3) of numpy's Σ g²/var_i / (N - 3), and its degrees of freedom N - 3
    exactly (they were N - 2 while the estimate's share was cut on the unscaled normal
    matrix, where the cubic coefficient's direction looked undetermined)."""
    cols = _calibration(seed)
    result = _solve(cols)
    assert result.success
    outliers = result.outliers
    assert outliers is not None and outliers.count == 0
    assert outliers.standardized_std is not None
    assert 0.93 < outliers.standardized_std["g_T"] < 1.07      # 1 ± 3 se of a MAD's spread
    g, sd = _numpy_g(cols, _th2(result))
    chi2 = float(np.sum((g / sd) ** 2))
    test = result.to_dict()["floor_tests"][0]
    assert test["dataset"] == "calibration"
    assert test["chi2"] == pytest.approx(chi2, rel=1e-6)
    assert test["chi2_dof"] == pytest.approx(chi2 / (g.size - 3), rel=1.01 / (g.size - 3))
    assert test["dof"] == pytest.approx(g.size - 3, abs=1e-6)


@pytest.mark.slow
def test_the_mean_chi2_of_clean_seeds_is_one() -> None:
    """Over 6 seeds the calibration χ²/dof averages 1 within 3 of its standard errors
    (sqrt(2/(6·1197)) = 0.017): the noise is propagated and simulated as declared (seed
    1000 alone, 0.904, is a low draw: its simulated noise's own std is 0.488 and 0.481
    ohm, and χ²/N at the true parameters 0.904 too)."""
    values = []
    for seed in range(1000, 1006):
        result = _solve(_calibration(seed))
        values.append(result.to_dict()["floor_tests"][0]["chi2_dof"])
    assert abs(np.mean(values) - 1.0) < 3 * np.sqrt(2.0 / (6 * 1197))


@pytest.mark.slow
def test_a_real_outlier_on_a_quiet_row_is_found() -> None:
    """12 ohm added to part 1's reading on a cold row (about 1.4 mK of noise there): a
    12 mK residual, within one spread of the noisy rows' residuals but 9 of its own
    standard deviations; it alone is found, its whitened residual as numpy's."""
    cols = _calibration(1002)
    row = 5                                         # the cold end of the sweep
    cols["R1"] = cols["R1"].copy()
    cols["R1"][row] += 12.0
    result = _solve(cols)
    outliers = result.outliers
    assert outliers is not None and [o.row for o in outliers.listed] == [row]
    g, sd = _numpy_g(cols, _th2(result))
    z = _numpy_z(g, sd)
    assert outliers.listed[0].whitened == pytest.approx(z[row], rel=1e-4)
    assert outliers.listed[0].residual == pytest.approx(g[row] * 1e3, rel=1e-6)   # mK
    assert not outliers.dominate
    # one spread for all rows does not see it
    assert abs(g[row] - np.median(g)) < THRESHOLD * MAD_TO_SIGMA * np.median(
        np.abs(g - np.median(g)))


@pytest.mark.slow
def test_dominating_outliers_of_a_propagated_fit_on_shards(tmp_path: Path) -> None:
    """Gross slips on 6 rows of the bath data dominate the propagated fit: the outliers,
    their refit with the propagated weights kept (the flagged rows set to 0) and the
    spread measured without them are the same by passes over shards as in memory."""
    from test_hugelog import differences, write_shards

    from symcal.calibrate.partitioned import solve_partitioned
    from symcal.solvers.executor import SerialExecutor

    cols = _calibration(1003)
    slipped = [50, 300, 555, 700, 901, 1150]
    cols["R2"] = cols["R2"].copy()
    cols["R2"][slipped] += 60.0
    problem = symcal.load_problem(BATH / "problem.yaml")
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    full = symcal.solve(problem, {"calibration": memory})
    outliers = full.outliers
    assert outliers is not None and outliers.dominate and outliers.squared
    assert sorted(o.row for o in outliers.listed) == slipped
    assert outliers.clean_std is not None and outliers.gross
    folder = write_shards(tmp_path / "log", cols, "npz", (400, 500, 300))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    assert differences(sharded.to_dict(), full.to_dict()) == []
