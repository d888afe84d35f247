"""A Result carries its problem, estimate and data; result.json round-trips; stale files are
refused; consumers of results never solve again."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, courier_data, write_csv

import symcal
import symcal.export.c
import symcal.language.yamlio
from symcal.base.errors import SymcalError
from symcal.revise.diagnose import diagnose
from symcal.revise.ladder import compare
from symcal.solvers import instrument

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"


@pytest.fixture
def project(tmp_path: Path, true_k: np.ndarray) -> dict[str, Path]:
    """A copy of the platen problem, its implicit overlay and models, with CSV data."""
    for sub in ("problems", "models"):
        shutil.copytree(ROOT / sub, tmp_path / sub)
    cal = write_csv(tmp_path / "cal.csv", courier_data(300, true_k, 5e-4, seed=3))
    fly = write_csv(tmp_path / "fly.csv", courier_data(200, true_k, 5e-4, seed=4))
    return {"problem": tmp_path / "problems" / "platen_self_calibration.yaml",
            "implicit": tmp_path / "problems" / "platen_self_calibration_implicit.yaml",
            "cal": cal, "fly": fly}


def _solve(path: Path, project: dict[str, Path]) -> symcal.Result:
    return symcal.solve(path, {"calibration": project["cal"], "flyby": project["fly"]})


def test_save_load_round_trip(project, tmp_path) -> None:
    result = _solve(project["problem"], project)
    path = result.save(tmp_path / "out" / "result.json")
    loaded = symcal.Result.load(path)
    assert loaded.problem.name == result.problem.name
    np.testing.assert_array_equal(loaded.theta, result.theta)
    np.testing.assert_array_equal(loaded.theta0, result.theta0)
    assert loaded.to_dict()["parameters"] == result.to_dict()["parameters"]
    assert loaded.to_dict()["stages"] == result.to_dict()["stages"]
    assert loaded.identifiability.null_space == result.identifiability.null_space
    np.testing.assert_allclose(loaded.uncertainty.covariance, result.uncertainty.covariance)
    for a, b in zip(loaded.statistics, result.statistics, strict=True):
        assert a.after.std == pytest.approx(b.after.std, rel=1e-12)
    assert (loaded.aic, loaded.bic) == pytest.approx((result.aic, result.bic), rel=1e-12)
    # the data come back from the files the result names
    np.testing.assert_array_equal(loaded.data["flyby"].columns["p2"],
                                  result.data["flyby"].columns["p2"])


def test_value_agrees_with_an_independent_evaluation(project) -> None:
    result = _solve(project["problem"], project)
    fly = result.data["flyby"].columns
    k = {n: p.value for n, p in result.params.items()}
    rho = 1.016

    def p_hat(i: int) -> np.ndarray:
        p = fly[f"p{i}"]
        f = 2 * np.pi / rho
        e = k[f"s{i}.k0"]
        for col, h in ((1, 1), (3, 2), (5, 4), (7, 6)):
            e = e + (k[f"s{i}.k{col}"] * np.sin(h * f * p)
                     + k[f"s{i}.k{col + 1}"] * np.cos(h * f * p))
        return p + e

    g_p = (p_hat(1) - p_hat(3)) - (p_hat(2) - p_hat(4))     # mm, internal
    # in the unit each quantity declares (g_p in um, theta_x in mrad), or as asked
    assert result.unit_of("g_p") == "um" and result.unit_of("theta_x") == "mrad"
    np.testing.assert_allclose(result.value("g_p", "flyby"), g_p / 1e-3, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.value("g_p", "flyby", unit="(internal)"), g_p, rtol=0,
                               atol=1e-12)
    # an expression (a comparison of the same name is reached as NAME only when no
    # constraint, expression or signal has it)
    np.testing.assert_allclose(result.value("theta_x", "flyby", unit="rad"),
                               (p_hat(1) - p_hat(3)) / 9.7, rtol=0, atol=1e-12)
    # a comparison: estimate − reference
    np.testing.assert_allclose(result.value("position_y", "flyby", unit="mm"),
                               (p_hat(2) + p_hat(4)) / 2 - fly["y_ref"], rtol=0, atol=1e-12)
    with pytest.raises(KeyError, match="no quantity 'g_q' \\(did you mean 'g_p'\\?\\)"):
        result.value("g_q")


def test_aic_bic_on_the_result_and_in_the_ladder(project) -> None:
    results = [_solve(project["problem"], project), _solve(project["implicit"], project)]
    rungs = compare(results)
    for rung, res in zip(rungs, results, strict=True):
        n, k = res.rows, res.identifiability.rank
        assert res.aic == pytest.approx(n * np.log(res.rss / n) + 2 * k)
        assert res.bic == pytest.approx(n * np.log(res.rss / n) + k * np.log(n))
        assert (rung.aic, rung.bic) == (res.aic, res.bic)
        # propagated weights (the bundled default): the RSS is the fitted dataset's χ²,
        # each row whitened by its own propagated covariance, not the plain Σ(g/σ)²
        assert res.problem.weighting == "propagated"
        fit = next(t for t in res.floor_tests if t.dataset == res.problem.fit_dataset)
        assert fit.method == "propagated" and res.rss == fit.chi2
        assert res.rss != pytest.approx(res.stages[-1].cost_after, rel=1e-3)


def test_a_changed_base_of_an_overlay_makes_the_result_stale(project, tmp_path) -> None:
    result = _solve(project["implicit"], project)
    path = result.save(tmp_path / "r.json")
    symcal.Result.load(path)                          # unchanged: accepted
    base = project["problem"]
    base.write_text(base.read_text() + "\n# edited\n")
    with pytest.raises(SymcalError) as err:
        symcal.Result.load(path)
    assert str(err.value) == (
        f"result file {path} was computed from another version of "
        f"{symcal.language.yamlio.display_path(base)} (it changed since the solve); "
        "solve again")


def test_a_changed_data_file_is_refused(project, tmp_path) -> None:
    path = _solve(project["problem"], project).save(tmp_path / "r.json")
    write_csv(project["fly"], courier_data(200, np.zeros((4, 9)), 5e-4, seed=9))
    loaded = symcal.Result.load(path)
    with pytest.raises(SymcalError, match="dataset 'flyby' .* changed since the result was "
                                          "computed; solve again"):
        loaded.data  # noqa: B018 - the data are read on first use


@pytest.mark.slow
def test_consumers_of_a_result_never_solve_again(project, tmp_path) -> None:
    result = _solve(project["problem"], project)
    loaded = symcal.Result.load(result.save(tmp_path / "r.json"))
    with instrument.counting() as counts:
        first = diagnose(result)
        again = diagnose(loaded)
        compare([result, loaded])
        symcal.export.c.generate(result.problem, tmp_path / "c", loaded)
    assert counts.iterations == 0 and counts.r_passes == 0
    assert [c.label for c in first.candidates] == [c.label for c in again.candidates]
    assert [c.f_stat for c in first.candidates] == pytest.approx(
        [c.f_stat for c in again.candidates], rel=1e-9)


def test_data_given_in_memory_are_not_silently_replaced(project, tmp_path) -> None:
    """A result solved on datasets passed as objects cannot read them again: loading its
    data is refused rather than silently reading the problem's own datasets."""
    data = symcal.load_datasets(symcal.load_problem(project["problem"]),
                                {"calibration": project["cal"], "flyby": project["fly"]})
    moved = {k: symcal.Dataset(k, "in memory", v.columns) for k, v in data.items()}
    path = symcal.solve(project["problem"], moved).save(tmp_path / "r.json")
    loaded = symcal.Result.load(path)
    with pytest.raises(SymcalError, match="was given as data in memory, not as a file"):
        loaded.data  # noqa: B018 - the data are read on first use


def test_a_reloaded_result_renders_byte_for_byte_the_same(tmp_path, monkeypatch) -> None:
    """Reports are functions of the Result (issue 21 item 5): the floors and tests are
    found at solve time and stored; rendering a loaded result reads no file and runs no
    simulation (both are made to fail here), and gives the same text and JSON."""
    import builtins

    import symcal.simulation.engine
    from symcal.report.text import json_report, text_report

    result = symcal.solve(ROOT / "problems" / "dual_sensor_calibration.yaml")
    text, doc = text_report(result), json_report(result)
    loaded = symcal.Result.load(result.save(tmp_path / "result.json"))

    def refuse(*args, **kwargs):
        raise AssertionError("a report read a file or simulated")

    monkeypatch.setattr(builtins, "open", refuse)
    monkeypatch.setattr(Path, "read_text", refuse)
    monkeypatch.setattr(Path, "read_bytes", refuse)
    for name in ("simulate_run", "simulate", "run_states", "truth"):
        monkeypatch.setattr(symcal.simulation.engine, name, refuse)
    again_text = text_report(loaded)
    again_doc = json_report(loaded)
    monkeypatch.undo()
    assert again_text == text
    assert again_doc == doc
    assert loaded.at_floor == result.at_floor
    assert [t.to_dict() for t in loaded.floor_tests] == [t.to_dict() for t in result.floor_tests]
