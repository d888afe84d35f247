"""Declared sensor noise (issue 22 item 1) and its propagation to every residual (item 2):
the key ``noise`` on a model input, a column, an instance and a problem's ``noise:``
section, units checked (exact error text); floors against an independent computation
(numpy finite differences, and a Monte Carlo of the declared noise through the model)."""

from __future__ import annotations

import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

import symcal
import symcal.simulation
from symcal.analysis.bands import chi2_band
from symcal.analysis.floors import floor_outcome
from symcal.analysis.row_noise import Fit, row_covariances
from symcal.base.errors import SpecError
from symcal.base.numeric import mapped
from symcal.data.dataset import make_dataset
from symcal.simulation import load_scenario, simulate_run

PROBLEMS = ROOT / "problems"
SCENARIOS = PROBLEMS / "scenarios"
UM = 1e-3

MODEL = """\
model: seg
constants:
  rho: {value: 1.016, unit: mm}
inputs:
  p: {unit: mm, period: rho, noise: 0.5 um}
parameters:
  k0: {value: 0, unit: mm}
  k1: {value: 0.01, unit: mm, scale: 0.01}
expressions:
  f: 2*pi/rho
  e: k0 + k1*sin(f*p)
outputs:
  p_hat: {expr: p + e, unit: mm}
"""

PROBLEM = """\
problem: demo
instances:
  s1: {model: seg.yaml, inputs: {p: p1}}
  s2: {model: seg.yaml, inputs: {p: p2}}
constraints:
  g: s1.p_hat - s2.p_hat
comparisons:
  pos: {estimate: s1.p_hat, reference: x_ref, unit: um}
datasets:
  calibration: {path: data.csv}
columns:
  t: {unit: s, role: time}
  p1: {unit: mm}
  p2: {unit: mm}
  x_ref: {unit: mm, noise: 0.1 um}
"""


def _load(tmp_path: Path, monkeypatch, model: str = MODEL, problem: str = PROBLEM
          ) -> symcal.Problem:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seg.yaml").write_text(textwrap.dedent(model))
    (tmp_path / "prob.yaml").write_text(textwrap.dedent(problem))
    return symcal.load_problem("prob.yaml")


def _sigmas(problem: symcal.Problem) -> dict[str, float]:
    return {r.name: r.sigma for r in problem.readings}


def test_noise_declared_on_inputs_and_columns(tmp_path, monkeypatch) -> None:
    problem = _load(tmp_path, monkeypatch)
    assert _sigmas(problem) == pytest.approx({"p1": 0.5e-3, "p2": 0.5e-3, "x_ref": 1e-4})
    origins = {r.name: r.origin for r in problem.readings}
    assert origins == {"p1": "model 'seg' input 'p'", "p2": "model 'seg' input 'p'",
                       "x_ref": "column 'x_ref'"}
    assert problem.weighting == "propagated" and not problem.study.weighting_declared


@pytest.mark.parametrize(("problem", "expected"), [
    # an instance overrides its model; the problem's noise: section overrides everything
    (PROBLEM.replace("inputs: {p: p2}}", "inputs: {p: p2}, noise: {p: 2 um}}"),
     {"p1": 0.5e-3, "p2": 2e-3, "x_ref": 1e-4}),
    (PROBLEM + "noise: {s1.p: 0.001, x_ref: 0 um}\n", {"p1": 1e-3, "p2": 0.5e-3, "x_ref": 0.0}),
    # a column's own noise is over its instances' and model's
    (PROBLEM.replace("  p2: {unit: mm}", "  p2: {unit: mm, noise: 3 um}"),
     {"p1": 0.5e-3, "p2": 3e-3, "x_ref": 1e-4}),
    # a plain number is in the reading's own unit
    (PROBLEM.replace("  p2: {unit: mm}", "  p2: {unit: um, noise: 4}"),
     {"p1": 0.5e-3, "p2": 4e-3, "x_ref": 1e-4}),
])
def test_noise_overrides(tmp_path, monkeypatch, problem, expected) -> None:
    assert _sigmas(_load(tmp_path, monkeypatch, problem=problem)) == pytest.approx(expected)


def test_a_time_column_is_exact_unless_its_noise_is_declared(tmp_path, monkeypatch) -> None:
    # a drift term reads the time: it must not leave the constraint's readings undeclared
    # (the weighting fell back to equal weights when symcal improve added one)
    drift = PROBLEM.replace("  g: s1.p_hat - s2.p_hat",
                            "  g: s1.p_hat - s2.p_hat + d*t\nparameters:\n"
                            "  d: {value: 0, unit: mm/s}")
    problem = _load(tmp_path, monkeypatch, problem=drift)
    readings = {r.name: (r.sigma, r.origin) for r in problem.readings}
    assert readings["t"] == (0.0, "column 't' (role: time: exact unless its noise is "
                                  "declared)")
    assert problem.undeclared(problem.constraint("g").sx) == []
    assert problem.weighting == "propagated"
    declared = _load(tmp_path, monkeypatch, problem=drift.replace(
        "t: {unit: s, role: time}", "t: {unit: s, role: time, noise: 2 ms}"))
    assert _sigmas(declared)["t"] == pytest.approx(2e-3)
    untimed = _load(tmp_path, monkeypatch, problem=drift.replace(
        "t: {unit: s, role: time}", "t: {unit: s, role: state}"))
    assert untimed.undeclared(untimed.constraint("g").sx) == ["t"]
    assert untimed.weighting == "equal"


@pytest.mark.parametrize(("unit", "period", "internal"), [
    ("deg", "360", 2 * np.pi),          # a plain number is in the input's unit (read as
    ("deg", "360 deg", 2 * np.pi),      # 360 rad before), or written with its own
    ("deg", "6.283185307179586 rad", 2 * np.pi),
    ("um", "5", 5e-3),
    ("mm", "rho", 1.016),               # an expression with a unit, as before
    ("rad", "2*pi", 2 * np.pi),
])
def test_a_period_is_in_the_inputs_unit_or_its_own(tmp_path, monkeypatch, unit, period,
                                                   internal) -> None:
    model = (f"model: seg\nconstants:\n  rho: {{value: 1.016, unit: mm}}\ninputs:\n"
             f"  p: {{unit: {unit}, period: {period}, noise: 0.5 {unit}}}\nparameters:\n"
             f"  k0: {{value: 0, unit: {unit}}}\noutputs:\n"
             f"  p_hat: {{expr: p + k0, unit: {unit}}}\n")
    problem = (f"problem: demo\ninstances:\n  s1: {{model: seg.yaml, inputs: {{p: p1}}}}\n"
               f"  s2: {{model: seg.yaml, inputs: {{p: p2}}}}\nconstraints:\n"
               f"  g: s1.p_hat - s2.p_hat\ndatasets:\n  calibration: {{path: data.csv}}\n"
               f"columns:\n  p1: {{unit: {unit}}}\n  p2: {{unit: {unit}}}\n")
    problem = _load(tmp_path, monkeypatch, model=model, problem=problem)
    found = next(q for q in problem.signals if q.name == "s1.p").period
    assert found == pytest.approx(internal, rel=1e-12)


def test_a_period_in_another_dimension_is_refused(tmp_path, monkeypatch) -> None:
    model = MODEL.replace("period: rho", "period: 1 rad")
    with pytest.raises(symcal.SpecError) as err:
        _load(tmp_path, monkeypatch, model=model)
    assert str(err.value).endswith("inputs.p.period: the period '1 rad' is in rad, an "
                                   "angle, but the input is in mm, a length")


def test_an_input_bound_to_an_expression_carries_its_own_noise(tmp_path, monkeypatch) -> None:
    problem = _load(tmp_path, monkeypatch, problem=PROBLEM.replace(
        "inputs: {p: p2}}", "inputs: {p: (p2 + p1)/2}}"))
    readings = {r.name: (r.kind, r.sigma) for r in problem.readings}
    assert readings == {"p1": ("column", 0.5e-3), "x_ref": ("column", 1e-4),
                        "s2.p": ("input", 0.5e-3)}
    # p2 is read only through s2.p's expression, and its own noise is not declared
    assert problem.undeclared(problem.constraint("g").sx) == ["p2"]
    assert problem.weighting == "equal"


def test_an_extending_problem_overrides_noise(tmp_path, monkeypatch) -> None:
    _load(tmp_path, monkeypatch)
    (tmp_path / "more.yaml").write_text("problem: more\nextends: prob.yaml\n"
                                        "instances:\n  s1: {noise: {p: 1 um}}\n"
                                        "noise: {x_ref: 0.2 um}\n")
    assert _sigmas(symcal.load_problem("more.yaml")) == pytest.approx(
        {"p1": 1e-3, "p2": 0.5e-3, "x_ref": 2e-4})


@pytest.mark.parametrize(("model", "problem", "message"), [
    (MODEL.replace("noise: 0.5 um", "noise: 0.5 rad"), PROBLEM,
     "seg.yaml:5: inputs.p.noise: the noise '0.5 rad' is in rad, an angle, but the reading "
     "is in mm, a length"),
    (MODEL.replace("noise: 0.5 um", "noise: -1 um"), PROBLEM,
     "seg.yaml:5: inputs.p.noise: a noise must be a finite standard deviation >= 0, found "
     "'-1 um'"),
    (MODEL.replace("noise: 0.5 um", "noise: half a micron"), PROBLEM,
     "seg.yaml:5: inputs.p.noise: 'half a micron' is not a noise: write a standard "
     "deviation with its unit, e.g. 'noise: 0.5 um'"),
    (MODEL.replace("noise: 0.5 um", "noise: 0.5 umm"), PROBLEM,
     "seg.yaml:5: inputs.p.noise: unknown unit 'umm' (did you mean 'mm'?); units are "
     "pint's (mm, um, m, rad, mrad, deg, s, mm/s, ...)"),
    (MODEL, PROBLEM.replace("x_ref: {unit: mm, noise: 0.1 um}", "x_ref: {unit: mm, noise: 1 s}"),
     "prob.yaml:15: columns.x_ref.noise: the noise '1 s' is in s, a time, but the reading is "
     "in mm, a length"),
    (MODEL, PROBLEM + "noise: {s3.p: 1 um}\n",
     "prob.yaml:16: noise.s3.p: 's3.p' is neither a column nor an instance input (did you "
     "mean 's1.p'?); 'noise:' names the readings whose noise it declares (a column such as "
     "'x_ref', or an input such as 's1.p')"),
    (MODEL, PROBLEM.replace("inputs: {p: p2}}", "inputs: {p: p2}, noise: {q: 1 um}}"),
     "prob.yaml:4: instances.s2.noise.q: 'q' is not an input of model 'seg'; it has: p"),
    (MODEL, PROBLEM.replace("inputs: {p: p1}}", "inputs: {p: p1}, noise: {p: 1 um}}")
     .replace("inputs: {p: p2}}", "inputs: {p: p1}, noise: {p: 2 um}}"),
     "prob.yaml:4: instances.s2.noise.p: column 'p1' has two noises: '2 um' (instance 's2' "
     "noise 'p') and '1 um' (instance 's1' noise 'p', prob.yaml:3: instances.s1.noise.p); "
     "declare its noise once, e.g. 'noise: {p1: ...}' in the problem"),
])
def test_noise_errors_name_file_line_key(tmp_path, monkeypatch, model, problem,
                                         message) -> None:
    with pytest.raises(SpecError) as err:
        _load(tmp_path, monkeypatch, model, problem)
    assert str(err.value) == message


def test_the_bundled_models_declare_the_scenarios_noise() -> None:
    """0.5 µm noise and a 0.2 µm step on the §3.1 platen, 1 µm and 0.2 µm on the §3.2 one,
    20 µrad on the coordination sensor: √(σ² + q²/12) as the simulator states it."""
    from symcal.simulation import input_noise

    for name, scenario in (("platen_self_calibration", "courier_platen"),
                           ("platen_self_calibration_implicit", "courier_platen"),
                           ("dual_sensor_calibration", "courier_dual"),
                           ("dual_sensor_calibration_implicit", "courier_dual")):
        problem = symcal.load_problem(PROBLEMS / f"{name}.yaml")
        truth = input_noise(load_scenario(SCENARIOS / f"{scenario}.yaml"))
        for r in problem.readings:
            if r.name.startswith(("p", "psi")):
                assert r.sigma == pytest.approx(truth[r.name], rel=2e-3), (name, r.name)
            else:       # the interferometer: negligible beside the sensors
                assert r.sigma < 0.02 * truth["p1"] or r.name == "theta_ref"
        assert problem.weighting == "propagated"


# ------------------------------------------------------------------ propagation


def _courier(problem: symcal.Problem, scenario: str, seed: int = 3) -> dict:
    sc = load_scenario(SCENARIOS / f"{scenario}.yaml")
    return {n: make_dataset(n, "simulated", simulate_run(sc, n, seed), [])
            for n in ("calibration", "flyby")}


def _fit(problem: symcal.Problem) -> Fit:
    return Fit("calibration", problem.stages[-1].constraints,
               np.zeros(len(problem.parameters), dtype=bool), "equal")


def test_floor_agrees_with_finite_differences() -> None:
    """The dual problem (nonlinear in its readings: tan(psi), rotations): the propagated
    covariance of (g_x, g_y, g_p) on every observation equals numpy's central differences
    of the residuals by each reading, times the declared variances."""
    problem = symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml")
    data = _courier(problem, "courier_dual")["calibration"]
    theta = np.array([p.value for p in problem.parameters])
    names = tuple(c.name for c in problem.constraints)
    cov = row_covariances(problem, names, data, theta)
    fn = mapped(problem.theta, problem.u, [c.sx for c in problem.constraints])
    u = data.matrix(problem.columns)
    sigma = {r.name: r.sigma for r in problem.readings}
    expected = np.zeros_like(cov)
    for i, col in enumerate(problem.columns):
        if col not in sigma:
            continue
        h = 1e-6 if col.startswith("p") else 1e-9
        up, down = u.copy(), u.copy()
        up[i] += h
        down[i] -= h
        d = (np.column_stack(fn(theta, up)) - np.column_stack(fn(theta, down))) / (2 * h)
        expected += sigma[col] ** 2 * np.einsum("ma,mb->mab", d, d)
    assert np.allclose(cov, expected, rtol=1e-5, atol=1e-12)
    # g_y's floor is the platen's angle noise through the 94.5 mm lever (l_x)
    floor = np.sqrt(cov[:, 1, 1].mean())
    assert 9.0 * UM < floor < 10.5 * UM


def test_row_covariances_kept_for_the_last_points() -> None:
    """A propagated solve asks for the row covariances at the same points again: the last
    two asked of a dataset are returned read-only, the same bits, and a third point, another
    dataset or another problem is computed again (equal to the first computation)."""
    problem = symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml")
    data = _courier(problem, "courier_dual")
    cal = data["calibration"]
    theta = np.array([p.value for p in problem.parameters])
    other = theta + 1e-3 * np.array([p.scale for p in problem.parameters])
    third = theta - 1e-3 * np.array([p.scale for p in problem.parameters])
    names = tuple(c.name for c in problem.constraints)
    first = row_covariances(problem, names, cal, theta)
    assert not first.flags.writeable
    assert row_covariances(problem, names, cal, theta) is first
    moved = row_covariances(problem, names, cal, other)
    assert not np.array_equal(moved, first)
    assert row_covariances(problem, names, cal, theta) is first      # still kept
    row_covariances(problem, names, cal, third)                      # first is dropped
    again = row_covariances(problem, names, cal, theta)
    assert again is not first and np.array_equal(again, first)
    flyby = row_covariances(problem, names, data["flyby"], theta)
    assert flyby.shape[0] == data["flyby"].n
    fresh = symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml")
    assert row_covariances(fresh, names, cal, theta) is not again


def test_floor_agrees_with_a_monte_carlo_of_the_declared_noise() -> None:
    """Declared noise added to noiseless readings 400 times: the residuals' standard
    deviation on every observation equals the propagated floor within its sampling error
    (first order is exact here to 1e-3)."""
    problem = symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml")
    sc = load_scenario(SCENARIOS / "courier_dual_clean.yaml")
    data = make_dataset("calibration", "noiseless",
                        simulate_run(symcal.simulation.quiet(sc), "calibration", 0, 50), [])
    theta = np.array([p.value for p in problem.parameters])
    names = tuple(c.name for c in problem.constraints)
    floor = np.sqrt(np.diagonal(row_covariances(problem, names, data, theta), axis1=1,
                                axis2=2))
    fn = mapped(problem.theta, problem.u, [c.sx for c in problem.constraints])
    u0 = data.matrix(problem.columns)
    sigma = np.array([next((r.sigma for r in problem.readings if r.name == c), 0.0)
                      for c in problem.columns])
    rng = np.random.default_rng(11)
    draws = np.stack([np.column_stack(fn(theta, u0 + sigma[:, None]
                                         * rng.standard_normal(u0.shape)))
                      for _ in range(400)])
    spread = draws.std(axis=0)
    # the standard deviation of 400 normal draws scatters by 1/sqrt(800) = 3.5 %
    assert np.all(np.abs(spread / floor - 1) < 5 * 0.035)
    assert abs(np.mean(spread / floor) - 1) < 0.01


def test_floor_of_g_p_is_twice_the_reading_noise_at_the_start() -> None:
    """At the design values (k = 0, ∂g_p/∂p = ±1) g_p's floor is 2 σ, and a comparison's
    includes its reference's declared noise."""
    problem = symcal.load_problem(PROBLEMS / "platen_self_calibration.yaml")
    data = _courier(problem, "courier_platen")
    theta = np.array([p.value for p in problem.parameters])
    outcome = floor_outcome(problem, data, theta, _fit(problem), keep=False)
    found, tests = outcome.tests, outcome.joint
    s = 0.503 * UM
    assert found[("calibration", "g_p")].floor == pytest.approx(2 * s, rel=1e-9)
    assert found[("flyby", "position_y")].floor == pytest.approx(
        np.sqrt(s**2 / 2 + (0.01 * UM) ** 2), rel=1e-9)
    assert [t.dataset for t in tests] == ["calibration", "flyby"]



def test_series_statistics_read_the_residuals_the_floors_evaluated() -> None:
    """The floors' pass evaluates every residual and comparison at the estimate and the
    start (the noisy view's expressions with the readings' errors at zero): the series
    statistics read those, the same bits as their own evaluation (numpy's residuals of
    the plain expressions agree), and evaluate again where the entries differ."""
    from symcal.analysis.fit import series_statistics
    from symcal.analysis.floors import Residuals

    problem = symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml")
    data = _courier(problem, "courier_dual")
    theta0 = np.array([p.value for p in problem.parameters])
    theta = theta0 + 1e-3 * np.array([p.scale for p in problem.parameters])
    outcome = floor_outcome(problem, data, theta, _fit(problem), theta0)
    assert set(outcome.residuals) == {"calibration", "flyby"}
    assert floor_outcome(problem, data, theta, _fit(problem), theta0, keep=False
                         ).residuals == {}
    own, _ = series_statistics(problem, data, theta0, theta)
    read, _ = series_statistics(problem, data, theta0, theta, outcome.residuals)
    assert read == own
    cal = outcome.residuals["calibration"]
    assert cal.before is not None
    fn = mapped(problem.theta, problem.u, [c.sx for c in problem.constraints])
    u = data["calibration"].matrix(problem.columns)
    for k, at in ((0, theta), (1, theta0)):
        mine = np.column_stack(fn(at, u))
        given = (cal.after, cal.before)[k][:, :mine.shape[1]]
        np.testing.assert_array_equal(given, mine)
    # read, not evaluated: residuals that differ give other statistics
    doubled = {**outcome.residuals,
               "calibration": Residuals(cal.names, 2 * cal.after, cal.before)}
    changed, _ = series_statistics(problem, data, theta0, theta, doubled)
    assert changed != own
    first = next(s for s in changed if s.dataset == "calibration")
    assert first.after.std == pytest.approx(
        2 * next(s for s in own if s.dataset == "calibration").after.std, rel=1e-12)
    # other entries than the series' own: evaluated as without them
    other = {"calibration": Residuals(cal.names[:-1], cal.after[:, :-1], cal.before[:, :-1])}
    assert series_statistics(problem, data, theta0, theta, other)[0] == own

def _timeless(doc):
    """A result document without its wall times."""
    if isinstance(doc, dict):
        return {k: _timeless(v) for k, v in doc.items() if k != "seconds"}
    if isinstance(doc, list):
        return [_timeless(v) for v in doc]
    return doc


@pytest.mark.parametrize("name, scenario, weighting", [
    ("dual_sensor_calibration", "courier_dual", None),        # propagated
    ("platen_self_calibration", "courier_platen", "equal"),
])
def test_a_solve_without_floors_gets_them_later_bit_for_bit(name, scenario,
                                                            weighting) -> None:
    """``improve``'s trials solve without the floors and add them to the revision kept:
    that is the solve's document bit for bit.  Without them the result's information
    criteria are already the solve's (propagated weights: the fitted dataset's χ², from
    one pass of its own), its only test that χ² without degrees of freedom or band."""
    from symcal.calibrate.solve import solve_without_floors, with_floors

    problem = symcal.load_problem(PROBLEMS / f"{name}.yaml")
    if weighting is not None:
        problem = problem.with_weighting(weighting)
    data = _courier(problem, scenario)
    start = {"s1.k1": 0.002}
    full = symcal.solve(problem, data, initial=start)
    lite = solve_without_floors(problem, data, start)
    assert (lite.rss, lite.bic, lite.aic) == (full.rss, full.bic, full.aic)
    np.testing.assert_array_equal(lite.theta, full.theta)
    assert all(s.noise is None for s in lite.statistics)
    if problem.weighting == "propagated":
        (test,) = lite.floor_tests
        assert (test.dataset, test.method, test.dof, test.band) == \
            ("calibration", "propagated", None, None)
        assert test.chi2 == next(t.chi2 for t in full.floor_tests
                                 if t.dataset == "calibration")
    else:
        assert lite.floor_tests == ()
    assert full.floor_tests and full.at_floor is not None
    assert _timeless(with_floors(lite).to_dict()) == _timeless(full.to_dict())


def test_the_fits_chi2_alone_declines_where_the_share_could_decide() -> None:
    """:func:`fit_chi2` is the joint test's χ² bit for bit; it declines (None) where the
    rows' ranks do not exceed the free parameters, whose test's degrees of freedom only
    the estimate's share tells."""
    from symcal.analysis.floors import fit_chi2

    problem = symcal.load_problem(PROBLEMS / "platen_self_calibration.yaml")
    data = _courier(problem, "courier_platen")
    theta = np.array([p.value for p in problem.parameters]) + 1e-3
    fit = replace(_fit(problem), weighting="propagated",
                  free=np.ones(len(problem.parameters), dtype=bool))
    joint = floor_outcome(problem, data, theta, fit).joint[0]
    alone = fit_chi2(problem, data["calibration"], theta, fit)
    assert alone is not None and alone.chi2 == joint.chi2 and joint.dof
    cal = data["calibration"]
    few = make_dataset("calibration", "first rows",
                       {k: v[:len(problem.parameters) - 1] for k, v in cal.columns.items()}, [])
    assert fit_chi2(problem, few, theta, fit) is None


def test_chi2_band_against_scipy() -> None:
    from scipy.stats import chi2

    for nu in (1, 2.5, 10, 50, 400, 967, 3000, 1e6):
        lo, hi = chi2_band(nu)
        assert lo == pytest.approx(chi2.ppf(0.025, nu) / nu, rel=1e-9)
        assert hi == pytest.approx(chi2.ppf(0.975, nu) / nu, rel=1e-9)


# --------------------------------------------------------- the band of an estimated floor


def test_beta_function_and_quantiles_against_scipy() -> None:
    from scipy import stats

    from symcal.analysis.bands import beta_cdf, beta_quantile

    for a, b in ((1.5, 2.5), (10.0, 30.0), (75.0, 74.0), (500.0, 499.0), (5e4, 5e4 + 7)):
        for x in (0.1, 0.3, 0.49, 0.5, 0.51, 0.7, 0.9):
            assert beta_cdf(x, a, b) == pytest.approx(stats.beta.cdf(x, a, b), abs=1e-10)
        for p in (0.0125, 0.025, 0.5, 0.975, 0.9875):
            assert beta_quantile(p, a, b) == pytest.approx(stats.beta.ppf(p, a, b), rel=1e-8)


def test_the_f_tests_log_tail_is_finite_where_the_tail_underflows() -> None:
    """The candidates' F-test ranks by the log of its tail.  Where scipy's tail is a
    normal number, the log equals scipy's; far beyond, where the tail underflows and
    scipy's ``logsf`` is −inf (every very significant candidate then tied), it equals the
    log of the density's integral taken in log space (an independent computation), and
    it keeps falling with the statistic."""
    from scipy import integrate, stats

    from symcal.analysis.bands import f_log_sf

    for d1 in (1, 2, 3, 7):
        for d2 in (5.0, 80.0, 3e3, 2e5, 4e6):
            for f in (0.05, 0.9, 1.3, 4.0, 30.0, 300.0):
                ref = stats.f.logsf(f, d1, d2)
                if stats.f.sf(f, d1, d2) > 1e-290:
                    assert f_log_sf(f, d1, d2) == pytest.approx(ref, rel=1e-7, abs=1e-12)
    for d1, d2, f in ((1, 1e4, 1e4), (2, 1e5, 1e5), (1, 3e3, 5e3), (3, 50.0, 1e20)):
        assert stats.f.logsf(f, d1, d2) == -np.inf          # what the ranking had
        peak = stats.f.logpdf(f, d1, d2)

        def scaled(t: float, d1: float = d1, d2: float = d2, f: float = f,
                   peak: float = peak) -> float:
            return float(np.exp(stats.f.logpdf(f * t, d1, d2) - peak) * f)

        # the density falls steeply from f: its first thousandth apart
        area = sum(integrate.quad(scaled, lo, hi, epsabs=0.0, epsrel=1e-12, limit=400)[0]
                   for lo, hi in ((1.0, 1.001), (1.001, 2.0), (2.0, np.inf)))
        ours = f_log_sf(f, d1, d2)
        assert np.isfinite(ours) and ours < -700
        assert ours == pytest.approx(peak + np.log(area), rel=1e-9)
        assert f_log_sf(1.01 * f, d1, d2) < ours
    assert f_log_sf(np.inf, 1, 10.0) == -np.inf and f_log_sf(0.0, 1, 10.0) == 0.0
    for tiny in (1e-300, 1e-30, 1e-12):       # 1 - x rounds to 0 in x = d2/(d2 + d1 f)
        assert f_log_sf(tiny, 1, 2017.0) == pytest.approx(stats.f.logsf(tiny, 1, 2017.0),
                                                          rel=1e-12)


@pytest.mark.parametrize("centred", [False, True])
@pytest.mark.parametrize("n", [60, 400])
def test_the_band_of_an_estimated_floor_holds_on_white_noise(n: int, centred: bool) -> None:
    """A residual of white noise, its floor estimated by successive differences on the same
    rows: 10000 draws fall beyond each end of the 95 % band 2.5 % of the time (binomial
    3σ: ±0.47 %); the normal band used before let 3.3-4.7 % above it.  The relative spread
    is the first-order one (8 % low at n = 60, 1 % at 400)."""
    from symcal.analysis.bands import ratio_band, ratio_sd

    rng = np.random.default_rng(11 + n + centred)
    r = rng.normal(size=(10_000, n)) + (3.0 if centred else 0.0)
    about = r - r.mean(axis=1, keepdims=True) if centred else r
    floor2 = np.sum(np.diff(r, axis=1) ** 2, axis=1) / (2 * (n - 1))
    value = np.sum(about**2, axis=1) / (n - 1 if centred else n) / floor2
    lo, hi = ratio_band(n, centred)
    tol = 3 * np.sqrt(0.025 * 0.975 / 10_000)
    assert abs(np.mean(value > hi) - 0.025) < tol
    assert abs(np.mean(value < lo) - 0.025) < tol
    assert ratio_sd(n, centred) == pytest.approx(np.std(value), rel=0.1)


def test_a_dataset_test_gives_its_band_at_any_level() -> None:
    from symcal.analysis.bands import normal_band, ratio_band
    from symcal.analysis.verdicts import DatasetTest

    chi2 = DatasetTest("a", ("g",), "propagated", 1000.0, 967.0, chi2_band(967.0))
    assert chi2.band_at(0.99) == pytest.approx(chi2_band(967.0, 0.99))
    wider = DatasetTest("a", ("g",), "propagated", 1000.0, 967.0, chi2_band(400.0),
                        "chi2", float(np.sqrt(2 / 400.0)))
    assert wider.band_at(0.99) == pytest.approx(chi2_band(400.0, 0.99))
    ratio = DatasetTest("a", ("g",), "combined", 300.0, 300.0, ratio_band(300), "ratio", 0.06)
    assert ratio.band_at(0.99) == pytest.approx(ratio_band(300, False, 0.99))
    normal = DatasetTest("a", ("g", "h"), "combined", 600.0, 600.0, normal_band(0.04),
                         "normal", 0.04)
    assert normal.band_at(0.99) == pytest.approx(normal_band(0.04, 0.99))
    for test in (chi2, wider, ratio, normal):
        again = DatasetTest.from_dict(test.to_dict())
        assert again == test and again.band_at(0.98) == test.band_at(0.98)
    old = {k: v for k, v in normal.to_dict().items() if k not in ("distribution", "sd")}
    assert DatasetTest.from_dict(old).band_at(0.99) is None     # a result.json from before


def test_at_floor_is_one_decision_for_the_datasets_together() -> None:
    """Two datasets: one just above its own 95 % band but inside the Šidák band (each at
    0.95^(1/2)) is at the floor with the other; the report keeps its own band and says
    why; a third dataset widens the family's bands further."""
    from symcal.analysis.verdicts import DatasetTest, at_floor, family_bands, family_level
    from symcal.report.text import family_note

    assert family_level(2) == pytest.approx(0.95 ** 0.5)
    own = chi2_band(400.0)
    family = chi2_band(400.0, 0.95 ** 0.5)
    assert family[1] > own[1]
    just = 0.5 * (own[1] + family[1]) * 400.0
    tests = (DatasetTest("calibration", ("g",), "propagated", 967.0, 967.0,
                         chi2_band(967.0)),
             DatasetTest("flyby", ("g",), "propagated", just, 400.0, own))
    assert tests[1].verdict == "above" and at_floor(tests) is True
    assert family_bands(tests)[1] == pytest.approx(family)
    assert family_note(tests, 0) == ""
    assert family_note(tests, 1) == (
        f"; at the floor as one of 2 datasets tested together (family-wise band "
        f"{family[0]:.2f}–{family[1]:.2f}, 95 % for all of them, Šidák)")
    far = tests[:1] + (DatasetTest("flyby", ("g",), "propagated", 1.5 * family[1] * 400.0,
                                   400.0, own),)
    assert at_floor(far) is False
    unknown = tests + (DatasetTest("more", ("g",), "unknown"),)
    assert at_floor(unknown) is None                # none off, one unknown
    three = tests + (DatasetTest("more", ("g",), "propagated", 400.0, 400.0, own),)
    assert family_bands(three)[1] == pytest.approx(chi2_band(400.0, 0.95 ** (1 / 3)))


def test_below_its_own_band_but_at_the_floor_with_the_others_is_not_a_failure() -> None:
    """A validation set just below its own band but inside the family's is at the floor
    with the calibration: its line said 'below the noise floor ... not a success; at the
    floor as one of 2 datasets tested together' under a verdict of every dataset at its
    floor."""
    from types import SimpleNamespace

    from symcal.analysis.verdicts import DatasetTest, at_floor
    from symcal.report.text import floor_lines

    own = chi2_band(400.0)
    family = chi2_band(400.0, 0.95 ** 0.5)
    just = 0.5 * (own[0] + family[0]) * 400.0
    tests = (DatasetTest("calibration", ("g",), "propagated", 967.0, 967.0,
                         chi2_band(967.0)),
             DatasetTest("validation", ("g",), "propagated", just, 400.0, own))
    assert tests[1].verdict == "below" and at_floor(tests) is True
    lines = floor_lines(SimpleNamespace(floor_tests=tests, statistics=()))
    assert lines[1].startswith("validation: below its own band (χ²/dof "), lines[1]
    assert "not a success" not in lines[1] and "as one of 2 datasets" in lines[1]
    far = tests[:1] + (DatasetTest("validation", ("g",), "propagated",
                                   0.5 * family[0] * 400.0, 400.0, own),)
    assert "not a success" in floor_lines(SimpleNamespace(floor_tests=far, statistics=()))[1]


def test_a_block_of_entries_is_the_same_picked_as_a_run_or_one_by_one() -> None:
    """The joint test's block of constraints: a run of consecutive entries is taken as a
    view, other picks gathered; either gives the values of ``a[:, idx][:, :, idx]``."""
    from symcal.analysis.floors import _block_of, _span

    a = np.arange(2 * 5 * 5, dtype=float).reshape(2, 5, 5)
    for idx in ((0, 1, 2), (1, 2), (3,), (0, 2), (4, 1)):
        picked = list(idx)
        got = _block_of(a, _span(idx))
        assert np.array_equal(got, a[:, picked][:, :, picked])
    assert isinstance(_span((1, 2, 3)), slice)
    assert _span((0, 2)) == [0, 2]
    assert _span((4, 1)) == [4, 1]


def test_increasing_root_finds_quantiles_in_flat_tails() -> None:
    """Regula falsi, the Illinois way: the root to within its tolerance, also where the
    bracket's ends lie deep in a flat tail and at an end that is the root."""
    from statistics import NormalDist

    from symcal.analysis.bands import increasing_root

    for p in (1e-6, 0.025, 0.5, 0.975):
        want = NormalDist().inv_cdf(p)
        f = lambda t, p=p: NormalDist().cdf(t) - p               # noqa: E731
        got = increasing_root(f, -40.0, 40.0, f(-40.0), f(40.0), 1e-9)
        assert abs(got - want) <= 1e-9, (p, got, want)
    steep = lambda t: 1.0 / (1.0 + np.exp(min(-200.0 * (t - 0.3), 700.0))) - 0.5   # noqa: E731
    assert increasing_root(steep, -5.0, 5.0, steep(-5.0), steep(5.0), 1e-12) == \
        pytest.approx(0.3, abs=1e-12)
    assert increasing_root(steep, 0.3, 5.0, 0.0, steep(5.0), 1e-12) == 0.3


@pytest.mark.parametrize(("n", "centred", "extra", "sd"), [
    (300, False, 30.0, 0.12), (600, True, 40.0, 0.08), (20_000, False, 900.0, 0.02)])
def test_the_shared_bands_quantiles_against_scipy(n, centred, extra, sd) -> None:
    """The band of an estimated floor with the estimate's share is the quantiles of a
    mixture over 64 equal-probability nodes of the share (``shared_ratio_band``'s
    docstring); the same mixture written here with scipy's beta and χ² and solved by
    ``brentq`` to 1e-12 gives the same band to 1e-7 of the degrees of freedom."""
    from scipy import optimize, stats

    from symcal.analysis.bands import _ratio_moments, ratio_sd, shared_ratio_band

    dof = n - centred + extra
    k = float(n - 1 if centred else n)
    mean_y, var_x = dof - k, (k * ratio_sd(n, centred)) ** 2
    var_y = (sd * dof) ** 2 - var_x
    cross = min(4.0 * mean_y, var_y) / mean_y
    var_q = var_y - cross * mean_y
    c, m1, var = _ratio_moments(n, centred)
    mu, v = m1 / 4.0, var / 16.0
    a, b = mu * (mu * (1 - mu) / v - 1), (1 - mu) * (mu * (1 - mu) / v - 1)
    f, scale = 2.0 * mean_y**2 / var_q, var_q / (2.0 * mean_y)
    nodes = scale * stats.chi2.ppf((np.arange(64) + 0.5) / 64, f)

    def cdf(t: float) -> float:
        noise = k + (t - nodes - k) / np.sqrt(1.0 + cross * np.maximum(nodes, 0) / var_x)
        x = c * k / (4.0 * np.where(noise > 0, noise, np.inf))
        return float(np.mean(np.where(noise > 0, stats.beta.sf(x, a, b), 0.0)))

    want = [optimize.brentq(lambda t, p=p: cdf(t) - p, 0.2 * dof, 3.0 * dof, xtol=1e-12)
            for p in (0.025, 0.975)]
    got = shared_ratio_band(n, centred, dof, sd)
    assert abs(got[0] * dof - want[0]) <= 1e-7 * dof and abs(got[1] * dof - want[1]) <= \
        1e-7 * dof, (got, [w / dof for w in want])


def test_a_shared_band_without_a_spread_is_no_band() -> None:
    """A NaN spread (no standard deviation to bracket the quantiles with) gives no band;
    the bracket's widening had never ended."""
    from symcal.analysis.bands import shared_ratio_band

    lo, hi = shared_ratio_band(300, False, 330.0, float("nan"))
    assert np.isnan(lo) and np.isnan(hi)
