"""Robust losses and outliers (issue 14, item 5).

- every loss finds scipy's minimum (``least_squares(loss=..., f_scale=...)``) on small curve
  fits, through the closed-form, trust-region and IPOPT paths;
- the sandwich covariance is the one computed independently with numpy, and honest over
  repeated draws;
- on simulated count slips (1 % of the observations), a robust loss recovers every
  identifiable parameter within 3 standard errors and names the slipped rows; with squared
  residuals the report and the diagnosis say that outliers dominate, and the loss they
  print, applied as printed on slips of 1 % and 5 %, lands within one standard error of a
  squared fit without the slipped rows (issue 25);
- the simulator's count slips are exactly where its truth says;
- bad ``loss:`` input is refused with an exact message.
"""

from __future__ import annotations

import re
from pathlib import Path

import courier_scenarios
import numpy as np
import pytest
import scipy.optimize
from conftest import ROOT

import symcal
from symcal.base.errors import SpecError
from symcal.data.dataset import make_dataset
from symcal.report.text import diagnosis_document, diagnosis_report, text_report
from symcal.revise.diagnose import diagnose
from symcal.simulation import load_scenario, simulate_run, slipped_rows, truth

LOSSES = ("huber", "soft_l1", "cauchy", "arctan")

DECAY = """\
problem: decay
columns: {{x: {{unit: s}}, y: {{unit: mm}}}}
parameters:
  a: {{value: 1, scale: 1}}
  k: {{value: 1, scale: 1}}
  b: {{value: 0, scale: 1}}
constraints:
  r: {{expr: y - a*exp(-k*x) - b, unit: um, loss: {{type: {loss}, scale: {scale}}}}}
datasets:
  calibration: {{path: d.csv}}
solver: {{method: {method}}}
"""

LINE = """\
problem: line
columns: {{x: {{unit: s}}, y: {{unit: mm}}}}
parameters:
  a: {{value: 0, scale: 1}}
  b: {{value: 0, scale: 1}}
constraints:
  r: {{expr: y - a - b*x, sigma: 0.5, loss: {{type: {loss}, scale: {scale}}}}}
datasets:
  calibration: {{path: d.csv}}
"""


def _write(folder: Path, x: np.ndarray, y: np.ndarray) -> None:
    rows = [f"{float(a)!r},{float(b)!r}" for a, b in zip(x, y, strict=True)]
    (folder / "d.csv").write_text("x,y\n" + "\n".join(rows) + "\n")


def _decay_data(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 5, 60)
    y = 2.5 * np.exp(-0.7 * x) + 0.3 + 0.01 * rng.normal(size=60)
    y[[5, 17, 40]] += [0.5, -0.4, 0.8]          # three gross errors
    return x, y


def _scipy(fun, x0, loss: str, f_scale: float) -> np.ndarray:
    sol = scipy.optimize.least_squares(fun, x0, loss=loss, f_scale=f_scale, method="trf",
                                       ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=10_000)
    assert sol.success
    return np.asarray(sol.x)


@pytest.mark.parametrize("loss", LOSSES)
def test_each_loss_finds_scipys_minimum_on_a_nonlinear_fit(tmp_path: Path, loss: str) -> None:
    x, y = _decay_data()
    _write(tmp_path, x, y)
    # the scale is in the constraint's unit (µm): 20 µm = 0.02 mm, scipy's f_scale
    (tmp_path / "fit.yaml").write_text(DECAY.format(loss=loss, scale=20, method="lm"))
    result = symcal.solve(tmp_path / "fit.yaml")
    assert result.success, result.stages[-1].message
    expected = _scipy(lambda p: y - p[0] * np.exp(-p[1] * x) - p[2], [1.0, 1.0, 0.0], loss,
                      0.02)
    np.testing.assert_allclose([result.params[n].value for n in "akb"], expected, rtol=1e-7)
    assert sorted(o.row for o in result.outliers.listed) == [5, 17, 40]


@pytest.mark.parametrize(("loss", "method"), [("cauchy", "auto"), ("huber", "ipopt")])
def test_the_closed_form_and_ipopt_paths_find_scipys_minimum(tmp_path: Path, loss: str,
                                                              method: str) -> None:
    rng = np.random.default_rng(5)
    x = np.linspace(-1, 3, 80)
    y = 0.4 + 1.7 * x + 0.5 * rng.normal(size=80)
    y[::13] += 9.0
    _write(tmp_path, x, y)
    text = LINE.format(loss=loss, scale=1.2)
    if method != "auto":
        text += f"solver: {{method: {method}}}\n"
    (tmp_path / "fit.yaml").write_text(text)
    result = symcal.solve(tmp_path / "fit.yaml")
    assert result.success, result.stages[-1].message
    assert result.stages[-1].method == ("linear" if method == "auto" else "ipopt")
    # σ = 0.5 whitens the residual: scipy sees (y - a - b x)/0.5 with f_scale 1.2/0.5
    expected = _scipy(lambda p: (y - p[0] - p[1] * x) / 0.5, [0.0, 0.0], loss, 2.4)
    rtol = 1e-9 if method == "auto" else 1e-6
    np.testing.assert_allclose([result.params[n].value for n in "ab"], expected, rtol=rtol)


def test_standard_errors_are_the_sandwich_with_the_final_weights(tmp_path: Path) -> None:
    """An independent computation: J analytic, W = ρ'(z) at the estimate, the meat from the
    covariance of ψ = W g with N - p degrees of freedom."""
    x, y = _decay_data()
    _write(tmp_path, x, y)
    (tmp_path / "fit.yaml").write_text(DECAY.format(loss="huber", scale=20, method="lm"))
    result = symcal.solve(tmp_path / "fit.yaml")
    a, k, b = (result.params[n].value for n in "akb")
    g = y - a * np.exp(-k * x) - b
    jac = np.column_stack([-np.exp(-k * x), a * x * np.exp(-k * x), -np.ones_like(x)])
    z = (g / 0.02) ** 2
    w = np.where(z <= 1, 1.0, 1.0 / np.sqrt(z))
    bread = np.linalg.inv(jac.T @ (w[:, None] * jac))
    psi = w * g
    s2 = float(psi @ psi) / (len(x) - 3)
    cov = bread @ (s2 * jac.T @ jac) @ bread
    se = [p.se for p in result.params.values()]
    np.testing.assert_allclose(se, np.sqrt(np.diag(cov)), rtol=1e-6)


@pytest.mark.slow
def test_robust_standard_errors_are_honest_over_repeated_draws(tmp_path: Path) -> None:
    """40 draws of a line with 3 % gross errors: (estimate - truth) / se has a standard
    deviation near 1 (its sampling spread over 80 values is about 8 %)."""
    (tmp_path / "fit.yaml").write_text(LINE.format(loss="huber", scale=1.0))
    problem = symcal.load_problem(tmp_path / "fit.yaml")
    rng = np.random.default_rng(11)
    x = np.linspace(-1, 3, 200)
    z = []
    for _ in range(40):
        y = 0.4 + 1.7 * x + 0.5 * rng.normal(size=x.size)
        bad = rng.uniform(size=x.size) < 0.03
        y[bad] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(5, 20, bad.sum())
        data = make_dataset("calibration", "drawn", {"x": x, "y": y}, ["x", "y"])
        result = symcal.solve(problem, {"calibration": data})
        z += [(result.params["a"].value - 0.4) / list(result.params.values())[0].se,
              (result.params["b"].value - 1.7) / list(result.params.values())[1].se]
    assert 0.8 < float(np.std(z)) < 1.2, np.std(z)


# --------------------------------------------------------------------------- count slips

PROBLEM = ROOT / "problems" / "platen_self_calibration.yaml"
SCENARIO = ROOT / "problems" / "scenarios" / "courier_platen.yaml"
SEED = 11
ROBUST = """\
problem: platen_robust
extends: {base}
constraints:
  g_p:
    expr: (s1.p_hat - s3.p_hat) - (s2.p_hat - s4.p_hat)
    unit: um
    loss: {{type: huber, scale: {scale}}}
"""


def _slipping(fraction: float = 0.01, segment: int = 0):
    """The default scenario with the model's assumptions (as in test_recovery) and count
    slips of one segment (s1) on ``fraction`` of the observations (every segment is
    listed, so that each draws from the slips' stream as the courier simulator did)."""
    fractions = {i: fraction if i == segment + 1 else 0.0 for i in range(1, 5)}
    return courier_scenarios.platen(courier_scenarios.count_slips(fractions))


@pytest.fixture(scope="module")
def slips(tmp_path_factory):
    scenario = _slipping()
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed=SEED), [])
            for name in ("calibration", "flyby")}
    squared = symcal.solve(symcal.load_problem(PROBLEM), data)
    folder = tmp_path_factory.mktemp("robust")
    (folder / "robust.yaml").write_text(ROBUST.format(base=PROBLEM, scale=2))
    robust = symcal.solve(symcal.load_problem(folder / "robust.yaml"), data)
    return scenario, data, squared, robust, folder


def _within(result: symcal.Result, scenario, limit: float) -> int:
    true = truth(scenario)["parameters"]
    checked = 0
    for p in result.params.values():
        if p.se is not None:
            assert abs(p.value - true[p.name]) < limit * p.se, (p.name, p.value,
                                                                 true[p.name], p.se)
            checked += 1
    for combo in result.identifiability.identifiable_combinations:
        value = sum(c * true[name] for name, c in combo.coefficients.items())
        assert abs(combo.value - value) < limit * combo.se, combo.text
    return checked


def test_a_robust_loss_recovers_every_parameter_within_three_standard_errors(slips) -> None:
    """Huber, scale 2 µm (about twice the noise).  With 32 parameters, "every one within 3
    standard errors" is itself a tail bound: measured over seeds 11-22 it holds on 83 % of
    the clean squared fits, 75-83 % of the Huber fits on 1 % slips (of s1 or s2) and
    8-25 % of the squared fits on the same slips; seed 11 is one where it holds."""
    scenario, _, _, robust, _ = slips
    assert robust.success, robust.stages[-1].message
    assert "iteratively reweighted" in robust.stages[-1].message
    assert _within(robust, scenario, 3.0) == 32


def test_the_robust_report_names_the_slipped_rows(slips) -> None:
    scenario, data, _, robust, _ = slips
    slipped = slipped_rows(scenario, "calibration", SEED)["p1"]
    assert 4 <= len(slipped) <= 20            # 1 % of 1000, drawn
    outliers = robust.outliers
    assert outliers.squared is False and not outliers.dominate
    assert sorted(o.row for o in outliers.listed) == slipped
    t = data["calibration"].columns["t"]
    text = text_report(robust)
    for o in outliers.listed:
        assert o.time == pytest.approx(t[o.row])
        assert o.weight < 0.05                 # down-weighted to a few percent
        assert re.search(rf"calibration\s+{o.row}\s+{o.time:.6g}\s+g_p\s", text), o.row
    doc = robust.to_dict()
    assert sorted(o["row"] for o in doc["outliers"]["listed"]) == slipped
    assert doc["outliers"]["loss"] == "g_p: huber, scale 2 µm"
    assert "robust sandwich with the final weights" in text


def test_with_squared_residuals_the_report_says_outliers_dominate(slips) -> None:
    scenario, _, squared, _, _ = slips
    outliers = squared.outliers
    assert outliers.squared and outliers.dominate
    assert sorted(o.row for o in outliers.listed) == slipped_rows(scenario, "calibration",
                                                                  SEED)["p1"]
    text = text_report(squared)
    verdict = text.split("\n\n")[1]
    assert "outliers dominate:" in verdict and "a robust loss is the remedy" in verdict
    assert squared.to_dict()["outliers"]["dominate"] is True
    # the squared fit is what a glitch in a hundred does: some parameter off by > 3 se
    with pytest.raises(AssertionError):
        _within(squared, scenario, 3.0)


def _printed_loss(squared: symcal.Result) -> tuple[str, float, str]:
    """The remedy diagnose prints for a squared fit: its type, scale, and the YAML."""
    diag = diagnose(squared)
    assert diag.outliers_dominate and diag.candidates == () and diag.tested == 0
    report = diagnosis_report(diag)
    remedy = diagnosis_document(diag)["outliers"]["remedy"]
    assert all(ln.strip() in report for ln in remedy.splitlines())
    match = re.fullmatch(r"constraints:\n  g_p:\n    loss: \{type: (\w+), scale: "
                         r"([0-9.e+-]+)\}    # beside its expr; scale in um\n", remedy)
    assert match is not None, remedy
    return match.group(1), float(match.group(2)), report


def _worst_gap(result: symcal.Result, reference: symcal.Result) -> float:
    """The largest difference of ``result`` from ``reference``, in the reference's standard
    errors, over every parameter and identifiable combination that has one."""
    gaps = [abs(p.value - q.value) / q.se
            for p, q in zip(result.params.values(), reference.params.values(), strict=True)
            if q.se]
    gaps += [abs(c.value - d.value) / d.se for c, d in zip(
        result.identifiability.identifiable_combinations,
        reference.identifiability.identifiable_combinations, strict=True)]
    return max(gaps)


def _without_slips(scenario, data, seed: int) -> symcal.Result:
    """The squared fit on the same data without the slipped rows: the answer."""
    rows = slipped_rows(scenario, "calibration", seed)["p1"]
    columns = data["calibration"].columns
    keep = np.ones(data["calibration"].n, dtype=bool)
    keep[rows] = False
    clean = make_dataset("calibration", "without the slips",
                         {k: np.asarray(v)[keep] for k, v in columns.items()}, [])
    return symcal.solve(symcal.load_problem(PROBLEM), {"calibration": clean})


def _applied(folder: Path, kind: str, scale: float, data) -> symcal.Result:
    (folder / "suggested.yaml").write_text(ROBUST.replace("huber", kind).format(
        base=PROBLEM, scale=scale))
    fixed = symcal.solve(symcal.load_problem(folder / "suggested.yaml"), data)
    assert fixed.success, fixed.stages[-1].message
    return fixed


@pytest.mark.slow
def test_diagnose_flags_outliers_before_missing_effects_and_its_yaml_works(slips) -> None:
    """The printed loss, applied as printed, lands within one standard error of the squared
    fit without the slipped rows (measured 0.34-0.77 on seeds 11 and 14-20 at 1 % and 5 %;
    the former suggestion, Huber at twice the squared fit's spread, 3.8-9.8 at 1 %)."""
    scenario, data, squared, _, folder = slips
    kind, scale, report = _printed_loss(squared)
    verdict = report.split("\n\n")[1]
    assert "where it fails: outliers dominate:" in verdict
    assert "what to add: a robust loss" in verdict
    assert report.index("Outliers (checked before missing effects") < report.index(
        "Which effect is missing: not examined, since outliers dominate")
    assert kind == "cauchy"                     # the slips are gross: a redescending loss
    assert 1.8 < scale < 3.0                    # 2.4 × the noise of g_p (about 1 µm)
    fixed = _applied(folder, kind, scale, data)
    assert _worst_gap(fixed, _without_slips(scenario, data, SEED)) < 1.0
    assert not fixed.outliers.dominate      # what diagnose checks first
    assert sorted(o.row for o in fixed.outliers.listed) == slipped_rows(
        scenario, "calibration", SEED)["p1"]


@pytest.mark.slow
@pytest.mark.parametrize(("fraction", "seed"), [(0.05, 11), (0.05, 14), (0.01, 14)])
def test_the_printed_loss_works_on_slips_of_one_and_five_percent(tmp_path: Path,
                                                                 fraction: float,
                                                                 seed: int) -> None:
    scenario = _slipping(fraction)
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed=seed), [])
            for name in ("calibration",)}
    squared = symcal.solve(symcal.load_problem(PROBLEM), data)
    kind, scale, _ = _printed_loss(squared)
    assert kind == "cauchy"
    fixed = _applied(tmp_path, kind, scale, data)
    assert _worst_gap(fixed, _without_slips(scenario, data, seed)) < 1.0
    assert _worst_gap(squared, _without_slips(scenario, data, seed)) > 10


def test_outliers_survive_save_and_load(slips) -> None:
    _, _, _, robust, folder = slips
    path = robust.save(folder / "result.json")
    loaded = symcal.Result.load(path, robust.problem)
    assert loaded.outliers == robust.outliers


def test_the_simulated_slips_are_where_the_truth_says() -> None:
    scenario = _slipping(0.05, segment=1)
    clean = scenario.overlay({"effects": {"count_slips": {"on": False}}})
    slipped = simulate_run(scenario, "calibration", seed=4, n=600)
    plain = simulate_run(clean, "calibration", seed=4, n=600)
    rows = truth(scenario, seed=4, n=600)["effects"]["count_slips"]["rows"]
    assert rows["calibration"] == slipped_rows(scenario, "calibration", 4, 600)
    for i in range(1, 5):
        jump = slipped[f"p{i}"] - plain[f"p{i}"]
        hit = np.flatnonzero(jump)
        assert hit.tolist() == rows["calibration"][f"p{i}"]
        np.testing.assert_allclose(np.abs(jump[hit]), 1.016 / 4, rtol=1e-12)
    assert 15 <= len(rows["calibration"]["p2"]) <= 45      # 5 % of 600 (binomial)
    assert {"t", "p1", "x_ref"} <= set(slipped) and slipped["t"].size == 600
    # a shorter run is a prefix of a longer one
    assert slipped_rows(scenario, "calibration", 4, 300)["p2"] == [
        r for r in rows["calibration"]["p2"] if r < 300]
    assert {c: v["fraction"] for c, v in truth(scenario)["effects"]["count_slips"][
        "slips"].items()} == {"p1": 0.0, "p2": 0.05, "p3": 0.0, "p4": 0.0}


def test_a_scenario_declares_count_slips(tmp_path: Path) -> None:
    clean = ROOT / "problems" / "scenarios" / "courier_platen_clean.yaml"
    path = tmp_path / "slips.yaml"
    path.write_text(f"scenario: slips\nextends: {clean}\neffects:\n"
                    "  count_slips: {slips: {p3: {fraction: 1.5, size: rho/4}}}\n")
    with pytest.raises(SpecError) as err:
        load_scenario(path)
    assert str(err.value).endswith("effects.count_slips.slips.p3.fraction: fraction is a "
                                   "share of the observations: expected a number from 0 to "
                                   "1, found 1.5")
    path.write_text(path.read_text().replace("1.5", "0.02"))
    effects = load_scenario(path).active_effects
    assert [e.name for e in effects] == ["count_slips"]
    assert [(s.column, s.fraction, s.size) for s in effects[0].slips] == [
        ("p3", 0.02, 1.016 / 4)]


# --------------------------------------------------------------------------- bad input

BAD = """\
problem: decay
columns: {x: {unit: s}, y: {unit: mm}}
parameters:
  a: {value: 1}
constraints:
  r:
    expr: y - a*x
    unit: um
    loss: LOSS
datasets:
  calibration: {path: d.csv}
"""


@pytest.mark.parametrize(("loss", "message"), [
    ("huber", "fit.yaml:9: constraints.r.loss: a robust loss needs a scale in the "
              "constraint's unit (µm): write loss: {type: huber, scale: NUMBER}"),
    ("{type: hubber, scale: 2}", "fit.yaml:9: constraints.r.loss.type: unknown loss 'hubber' "
                                 "(did you mean 'huber'?); losses: huber, soft_l1, cauchy, "
                                 "arctan (squared residuals without 'loss')"),
    ("{type: cauchy, scale: -2}", "fit.yaml:9: constraints.r.loss.scale: the scale of a "
                                  "robust loss must be positive, found -2 (it is where the "
                                  "loss stops being quadratic, in µm)"),
    ("{type: cauchy, scale: two}", "fit.yaml:9: constraints.r.loss.scale: expected a number, "
                                   "found text ('two')"),
    ("{type: arctan}", "fit.yaml:9: constraints.r.loss: missing required key 'scale'"),
    ("{type: arctan, scale: 1, f_scale: 2}", "fit.yaml:9: constraints.r.loss.f_scale: "
                                             "unknown key 'f_scale' (did you mean 'scale'?); "
                                             "allowed keys: type, scale"),
])
def test_bad_loss_input_gives_an_exact_error(tmp_path: Path, monkeypatch, loss: str,
                                             message: str) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "fit.yaml").write_text(BAD.replace("LOSS", loss))
    with pytest.raises(SpecError) as err:
        symcal.load_problem("fit.yaml")
    assert str(err.value) == message


def test_a_loss_with_estimated_weighting_is_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    text = BAD.replace("LOSS", "{type: huber, scale: 3}") + "weighting: estimated\n"
    (tmp_path / "fit.yaml").write_text(text)
    with pytest.raises(SpecError) as err:
        symcal.load_problem("fit.yaml")
    assert str(err.value) == ("fit.yaml:9: constraints.r.loss: constraint 'r' declares a "
                              "robust loss, which 'weighting: estimated' does not support: "
                              "remove one of them")


@pytest.mark.parametrize(("size", "kind", "factor"), [(4.0, "huber", 1.345),
                                                      (40.0, "cauchy", 2.3849)])
def test_the_remedy_measures_the_noise_without_the_outliers(size: float, kind: str,
                                                            factor: float) -> None:
    """find_outliers against numpy: a line with 6 outliers of ``size`` (noise 0.5, so 8
    and 80 noise spreads); the refit is numpy's least squares without the rows set aside."""
    from symcal.analysis.outliers import find_outliers, remedy_yaml, robust_std

    rng = np.random.default_rng(8)
    x = np.linspace(-1, 3, 80)
    y = 0.4 + 1.7 * x + 0.5 * rng.normal(size=80)
    bad = np.arange(3, 80, 13)
    y[bad] += size
    a = np.column_stack([np.ones_like(x), x])

    def residuals(keep: np.ndarray) -> np.ndarray:
        coef = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
        return (y - a @ coef)[:, None]

    def refit(aside: np.ndarray) -> np.ndarray:
        return residuals(~aside[:, 0])

    g = residuals(np.ones(80, dtype=bool))
    found = find_outliers("calibration", ("r",), ("mm",), np.array([1.0]), g, None,
                          "squared", refit=refit)
    assert found.dominate and sorted(o.row for o in found.listed) == bad.tolist()
    keep = np.ones(80, dtype=bool)
    keep[bad] = False
    clean = robust_std(residuals(keep)[keep, 0])
    assert found.clean_std == {"r": pytest.approx(clean, rel=1e-12)}
    assert found.gross is (kind == "cauchy")
    assert found.robust_std["r"] > clean          # the squared fit's spread is inflated
    assert remedy_yaml(found) == ("constraints:\n  r:\n    loss: {type: " + kind + ", scale: "
                                  f"{float(f'{factor * clean:.2g}'):g}}}    # beside its "
                                  "expr; scale in mm\n")
