"""The loop closes (issue 12): on the project's simulated courier with one hidden effect
each (errors applied where physics applies them, so the explicit model's own
approximation is there too), `symcal improve` ends quiet at the noise floor, on the
calibration and the held-out fly-by, in few rounds, with the true effect named first and
its coefficient within 3 standard errors of the truth; what the constraints cannot
determine is reported apart; every printed suggestion loads as written."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import courier_scenarios
import numpy as np
import pytest
from conftest import ROOT

import symcal
import symcal.simulation
from symcal.base.files import write_output
from symcal.base.numeric import mapped
from symcal.cli import main
from symcal.data.dataset import make_dataset, write_table
from symcal.revise.diagnose import diagnose
from symcal.revise.effects import write_revision
from symcal.revise.improve import improve
from symcal.simulation import load_scenario, simulate_run

PROBLEMS = ROOT / "problems"
EXPLICIT = PROBLEMS / "platen_self_calibration.yaml"
IMPLICIT = PROBLEMS / "platen_self_calibration_implicit.yaml"

#: case -> (effects, the true candidate (or a member of its group), parameter suffix and
#: true coefficients of the term symcal adds, sign of the instance it may land on)
CASES = {
    "harmonic": (courier_scenarios.harmonic(2, 3, sin=0.002, cos=-0.0015),
                 "s2.p_hat += harmonic 3 of s2.p (period 1.016 mm)"),
    "drift": (courier_scenarios.drift(1, rate=2e-5),
              "s1.p_hat += a slow drift in time (t)"),
    "angle-dependent gain": (courier_scenarios.angle(3, a=0.3),
                             "s3.p_hat += a term linear in theta_raw"),
}


def _scenario(*effects: dict):
    """The courier's physics (errors at the true position) with small angles, 0.5 um
    noise and ``effects``."""
    return courier_scenarios.platen(*effects, model=False)


def _data(scenario, seed: int) -> dict[str, symcal.Dataset]:
    return {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed), [])
            for name in ("calibration", "flyby")}


@pytest.mark.slow
def test_above_the_floor_with_no_candidate_left_is_not_quiet(tmp_path, capsys) -> None:
    """Readings twice as noisy as declared (1 µm, the model says 0.503 µm): no candidate
    is significant, the residuals are twice the floor; improve keeps nothing, ends not
    quiet with exit 1 and says that structure remains that no candidate explains (or the
    noise is larger than declared), never quiet at exit 0."""
    sc = load_scenario(PROBLEMS / "scenarios" / "courier_platen_clean.yaml")
    noisy = dataclasses.replace(sc, columns=tuple(
        dataclasses.replace(c, noise=1e-3) if c.name in ("p1", "p2", "p3", "p4") else c
        for c in sc.columns))
    paths = {}
    for name in ("calibration", "flyby"):
        paths[name] = tmp_path / f"{name}.csv"
        write_table(paths[name], simulate_run(noisy, name, 4))
    argv = ["improve", str(IMPLICIT), "--data", f"calibration={paths['calibration']}",
            "--data", f"flyby={paths['flyby']}", "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*argv, "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["quiet"] is False and doc["at_floor"] is False
    assert [r["added"] for r in doc["rounds"]] == [None]
    assert doc["rounds"][0]["significant"] == 0
    for entry in doc["rounds"][0]["statistics"]:
        assert set(entry) >= {"floor", "chi2_dof"}
        if entry["kind"] == "constraint":
            assert entry["chi2_dof"] > 3 and 1.0 < entry["floor"] < 1.1   # µm
    left = doc["left"]        # what diagnose says is left, as the text's lines say it
    assert isinstance(left, list) and all(isinstance(line, str) for line in left)
    assert main(argv) == 1
    out = capsys.readouterr().out
    said = [line.removeprefix("  what is left above the floor: ") for line in
            out.splitlines() if line.startswith("  what is left above the floor: ")]
    assert said == left[:3]
    assert out.splitlines()[0] == (
        "symcal improve: 0 round(s) kept; the diagnosis is not quiet: structure remains that "
        "no candidate explains (above the noise floor, and no candidate of the library is "
        "significant; or the readings are noisier than declared)")
    assert out.splitlines()[2].startswith("  calibration: 2.")


def _realized_floor(seed: int) -> float:
    """g_p's spread on the fly-by at the true parameters of the exact model (the implicit
    one, no hidden effect) for this noise realization: the floor a held-out dataset can
    reach (the noise streams do not depend on the effects)."""
    scenario = _scenario()
    flyby = _data(scenario, seed)["flyby"]
    problem = symcal.load_problem(IMPLICIT)
    true = symcal.simulation.truth(scenario)["parameters"]
    theta = np.array([true[n] for n in problem.parameter_names])
    fn = mapped(problem.theta, problem.u, [problem.constraint("g_p").sx])
    return float(np.std(fn(theta, flyby.matrix(problem.columns))[0]))


def _ratio(result: symcal.Result, scenario, dataset: str, seed: int) -> float:
    """g_p's spread over its floor: on the calibration data the noise floor allowing for
    the degrees of freedom the fit used; on the fly-by the realized floor."""
    if dataset == "calibration":
        floor = courier_scenarios.floors(result.problem, scenario)["g_p_std"] * np.sqrt(
            result.uncertainty.dof / result.rows)
    else:
        floor = _realized_floor(seed)
    return result.stat("g_p", dataset, unit="mm").after.std / floor


def _named(diag, truth: str) -> bool:
    """The truth leads or is in the leading group (a harmonic of the reading is named by
    where the model evaluates its error: the raw reading p, or u in an implicit model)."""
    lead = diag.significant[0]
    group = {label.replace(".u (", ".p (") for label in (lead.label, *lead.indistinguishable)}
    return truth in group


def _fitted(result: symcal.Result, case: str, scenario, seed: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The added term's coefficients, their standard errors and the truth, in the sign
    of the instance the term landed on (g_p = (p1 - p3) - (p2 - p4): s1 and s4 enter with
    one sign, s2 and s3 with the other).

    The angle-dependent gain acts on the true angle and the model can only use the
    uncalibrated theta_raw; but θ_raw - θ is a sum of the segments' modelled errors, which
    the fit compensates through their coefficients, so the coefficient of theta_raw is
    the gain itself (no errors-in-variables attenuation)."""
    params = dict(result.params)
    if case == "harmonic":
        names = sorted((n for n in params if re.fullmatch(r"s[24]\.h3_(sin|cos)_[pu]", n)),
                       key=lambda n: "_cos_" in n)   # sin first, as Harmonic(n, sin, cos)
        sign = 1.0 if names[0].startswith("s2") else -1.0     # s4: the other sign
        truth = sign * np.array([0.002, -0.0015])
    elif case == "drift":
        names = [n for n in params if n.endswith(".drift_t")]
        sign = 1.0 if names[0][:2] in ("s1", "s4") else -1.0
        truth = sign * np.array([2e-5])
    else:
        names = [n for n in params if n.endswith(".lin_theta_raw")]
        sign = 1.0 if names[0][:2] in ("s2", "s3") else -1.0   # same sign as s3 in g_p
        truth = sign * np.array([0.3])
    value = np.array([params[n].value for n in names])
    se = np.array([params[n].se for n in names])
    return value, se, truth


@pytest.mark.slow
def test_clean_data_is_quiet_after_the_approximation(tmp_path) -> None:
    """No hidden effect: starting explicit, the model's own approximation is the one
    finding, switching to the implicit model reaches the floor and the diagnosis is
    quiet; starting implicit it is quiet at once."""
    scenario = _scenario()
    data = _data(scenario, seed=61)
    result = improve(EXPLICIT, tmp_path / "explicit", data)
    assert [r.added for r in result.rounds] == [None, symcal.revise.diagnose.APPROXIMATION]
    assert result.quiet
    final = result.rounds[-1].result
    assert _ratio(final, scenario, "calibration", 61) < 1.05
    assert _ratio(final, scenario, "flyby", 61) < 1.05
    assert not diagnose(symcal.solve(IMPLICIT, data)).significant


#: Each hidden effect from either start, on one of two seeds (the 12 combinations of two
#: seeds × three effects × two starts passed on 2026-11-27; the acceptance runner,
#: benchmarks/acceptance.py, runs such cases on more systems and seeds).
ONE_EACH = [(71, "harmonic", "explicit"), (72, "harmonic", "implicit"),
            (72, "drift", "explicit"), (71, "drift", "implicit"),
            (71, "angle-dependent gain", "implicit"), (72, "angle-dependent gain", "explicit")]


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "case", "start"), ONE_EACH)
def test_one_hidden_effect_is_named_and_fixed(case, start, seed, tmp_path) -> None:
    effects, truth = CASES[case]
    scenario = _scenario(effects)
    data = _data(scenario, seed)
    problem = EXPLICIT if start == "explicit" else IMPLICIT
    first = diagnose(symcal.solve(problem, data))
    labels = [first.significant[0].label, *first.significant[0].indistinguishable]
    if start == "implicit" or first.significant[0].basis.kind != "approximation":
        assert _named(first, truth), labels
    else:   # the approximation first, then the effect
        assert _named(first, symcal.revise.diagnose.APPROXIMATION)
    result = improve(problem, tmp_path / "out", data)
    assert not result.candidates_left, [r.added for r in result.rounds]
    assert len(result.rounds) - 1 <= (3 if start == "explicit" else 2)
    final = result.rounds[-1].result
    # quiet only at the floor, by the global test of each dataset at 95 %: with two
    # datasets an exact model is off a band in about 1 run of 10 (seed 71's angle gain
    # ends with the fly-by's χ²/dof at 1.149 over a band ending at 1.14: not quiet)
    assert result.quiet == (final.at_floor is True)
    assert _ratio(final, scenario, "calibration", seed) < 1.10
    assert _ratio(final, scenario, "flyby", seed) < 1.10
    value, se, true = _fitted(final, case, scenario, seed)
    assert np.all(np.abs(value - true) < 3 * se), (value, se, true)


@pytest.mark.slow
def test_lateral_dependence_is_not_calibratable_from_g_p() -> None:
    """A lateral term of s1 is absorbed by s4's own harmonics in g_p: reported apart, with
    the dual problem (which has g_x, g_y on the same sensors) as what can determine it,
    and never suggested."""
    scenario = _scenario(courier_scenarios.lateral(1, 0.006, -0.003))
    diag = diagnose(symcal.solve(EXPLICIT, _data(scenario, seed=62)))
    truth = "s1.p_hat += harmonic 1 of s4.p (period 1.016 mm)"
    uncal = {m for c in diag.uncalibratable for m in (c.label, *c.indistinguishable)}
    assert truth in uncal
    lead = next(c for c in diag.uncalibratable
                if truth in (c.label, *c.indistinguishable))
    needs = diag.needs[lead.label]
    assert "dual_sensor_calibration.yaml in the same folder adds the constraints g_x, g_y" \
        in needs
    suggested = {m for c in diag.significant for m in (c.label, *c.indistinguishable)}
    assert truth not in suggested
    assert all("harmonic 1 of s4.p" not in text for text in diag.yaml.values())
    doc = diag.to_dict()
    assert any(truth in (u["label"], *u["indistinguishable"]) for u in doc["uncalibratable"])


@pytest.mark.slow
@pytest.mark.parametrize(("case", "start"), [("harmonic", IMPLICIT), ("drift", IMPLICIT),
                                             ("clean", EXPLICIT)])
def test_predictions_are_what_solving_again_gives(case, start, tmp_path) -> None:
    """For the candidate the loop applies, the predicted spreads on every dataset,
    held-out ones included, are within 20 % of what solving again with it gives (for the
    explicit problem on clean data the candidate is the switch to the implicit model)."""
    effects = () if case == "clean" else (CASES[case][0],)
    data = _data(_scenario(*effects), seed=63)
    problem = symcal.load_problem(start)
    diag = diagnose(symcal.solve(problem, data))
    lead = diag.significant[0]
    if lead.basis.kind == "approximation":
        assert diag.variant is not None
        revised = diag.variant.problem
    else:
        from symcal.revise.effects import revised_problem

        revised = revised_problem(problem, lead, tmp_path)
    again = symcal.solve(revised, data)
    for key, (_, predicted) in lead.reduction.items():
        dataset, name = key.split("/")
        stat = again.stat(name, dataset)
        actual = stat.shown("after").size(stat.remove_mean)      # the RMS it predicts
        assert predicted == pytest.approx(actual, rel=0.2), (lead.label, key)
        scatter = lead.scatter[key][1]
        assert scatter == pytest.approx(stat.shown("after").std, rel=0.2), (lead.label, key)


@pytest.mark.slow
def test_a_candidate_left_unsolved_for_a_reference_would_have_been_refused(
        tmp_path, monkeypatch) -> None:
    """The dual courier's last round: once the held-out check judged RMS too, ten
    candidates the diagnosis predicted to make a reference comparison 13-95 % worse were
    each solved and refused for it (6.6 s for the round).  Those predicted worse by more
    than the check allows (with a margin) are not solved; solved anyway, each is refused."""
    from symcal.revise import improve as loop

    skipped = []
    predicted_worse = loop._predicted_worse

    def spy(diag, labels):
        why = predicted_worse(diag, labels)
        if why is not None and "against the reference" in why:
            skipped.append((diag, list(labels), why))
        return why

    monkeypatch.setattr(loop, "_predicted_worse", spy)
    improve(PROBLEMS / "dual_sensor_calibration_implicit.yaml", tmp_path / "out")
    assert len(skipped) >= 3
    for i, (diag, labels, why) in enumerate(skipped):
        assert re.fullmatch(r"not solved: the diagnosis predicts that \S+ theta_[xy] against "
                            r"the reference gets worse \([0-9.]+ → [0-9.]+ \S+\)", why), why
        cands = [next(c for c in diag.candidates if c.label == label) for label in labels]
        path = write_revision(diag.result.problem, cands[0], tmp_path / "again",
                              f"again{i}", tuple(cands[1:]))
        new = loop._trial(symcal.load_problem(path), diag.result.data, diag.result)
        assert loop._pays(new, diag.result, 0.01) is not None, labels


@pytest.mark.slow
def test_a_candidate_left_unsolved_would_have_been_refused(tmp_path, monkeypatch) -> None:
    """The loop does not solve a candidate whose held-out constraint residuals the
    diagnosis predicts to grow (their RMS and their standard deviation alike); solved
    anyway, each of them is refused for it.  A thermistor bath whose second thermistor
    lags by a step that follows the sweep's direction: after the first round, the
    diagnosis predicts both sizes to grow for a delay and a drift."""
    from symcal.revise import improve as loop

    bath = ROOT / "tests" / "acceptance" / "thermistor_bath"
    scenario = load_scenario(bath / "scenario_hysteresis.yaml")
    data = {k: make_dataset(k, "simulated", simulate_run(scenario, k, 1000), [])
            for k in ("calibration", "validation")}

    skipped = []
    predicted_worse = loop._predicted_worse

    def spy(diag, labels):
        why = predicted_worse(diag, labels)
        if why is not None:
            skipped.append((diag, list(labels), why))
        return why

    monkeypatch.setattr(loop, "_predicted_worse", spy)
    outcome = improve(bath / "problem.yaml", tmp_path / "out", data, max_rounds=2)
    assert skipped and all(("; ".join(labels), why) in outcome.rejected
                           for _, labels, why in skipped)
    for i, (diag, labels, why) in enumerate(skipped):
        assert why.startswith("not solved: the diagnosis predicts that the held-out "
                              "constraint residuals do not fall (mean change +")
        cands = [next(c for c in diag.candidates if c.label == label) for label in labels]
        path = (loop._revision(diag, labels[0], tmp_path / "again", f"again{i}")
                if len(labels) == 1 else   # the model's approximation too
                write_revision(diag.result.problem, cands[0], tmp_path / "again",
                               f"again{i}", tuple(cands[1:])))
        new = loop._trial(symcal.load_problem(path), diag.result.data, diag.result)
        assert loop.held_out_change(new, diag.result, "constraint") >= 0, labels
        assert loop._pays(new, diag.result, 0.01) is not None, labels


def test_a_moved_parameter_nearly_aliased_with_the_term_is_not_called_biased() -> None:
    # a thermometer's quadratic stand-in moved its offset 623 se, correlated -1.0000 with
    # it: "the old estimates were biased by the missing effect" claimed too much
    from symcal.revise.watch import Moved, Watch

    moved = (Moved("tc.o", 0.1287, 0.0027, 1.80, 0.18, "K"),)
    tied = Watch(moved, (("tc.quad_T_tc", "tc.o", -1.0),), (), "", True).words("q")
    assert not any("biased by" in line for line in tied)
    assert tied[-2].endswith(
        ": the model is now at its noise floor, but tc.o is nearly aliased with the new "
        "term (below): the new values depend on how the term is written (its variable, "
        "its centre) as much as on the data, and the term may stand in for another effect")
    grown = Watch(moved, (), (("tc.o", 0.0027, 0.18),), "", True).words("q")
    assert "but tc.o is nearly aliased" in grown[0]
    alone = Watch(moved, (), (), "", True).words("q")
    assert alone[-1].endswith(": the old estimates were biased by the missing effect (the "
                              "model is now at its noise floor)")


def test_a_revision_weighted_otherwise_is_not_compared() -> None:
    from symcal.revise.improve import _pays

    problem = symcal.load_problem(ROOT / "examples" / "hidden_effect" / "problem.yaml")
    old = symcal.solve(problem)
    new = symcal.solve(problem.with_weighting("equal"))
    assert old.problem.weighting == "propagated" and new.success
    assert _pays(new, old, 0.01) == ("the weighting changes from 'propagated' to 'equal' "
                                     "and the BIC does not compare")


@pytest.mark.slow
def test_a_prediction_for_siblings_together_is_what_solving_again_gives(tmp_path) -> None:
    """The diagnosis's joint prediction for a lead and its siblings added at once (what
    the loop reads before solving them) is within 20 % of solving again with them all;
    for one candidate it is that candidate's own prediction."""
    from symcal.revise.improve import siblings

    result = symcal.solve(IMPLICIT)
    diag = diagnose(result, report=False)
    lead = next(c for c in diag.significant if c.label.startswith("s2.p_hat += harmonic 3"))
    also = siblings(diag, lead)
    assert len(also) == 3 and diag.together is not None
    assert diag.together([lead.label]) == (lead.reduction, lead.scatter)
    sizes, scatter = diag.together([c.label for c in (lead, *also)])
    path = write_revision(result.problem, lead, tmp_path, "all", also)
    again = symcal.solve(path, result.data)
    assert again.success
    for key, (now, new) in sizes.items():
        dataset, name = key.split("/")
        before, after = result.stat(name, dataset), again.stat(name, dataset)
        assert now == pytest.approx(before.shown("after").size(before.remove_mean))
        assert new == pytest.approx(after.shown("after").size(after.remove_mean),
                                    rel=0.2), key
        assert scatter[key][0] == pytest.approx(before.shown("after").std)
        assert scatter[key][1] == pytest.approx(after.shown("after").std, rel=0.2), key


def _apply_printed(text: str, home: Path) -> Path:
    """Write the files a printed suggestion names, as a user would; return the overlay."""
    files: dict[Path, list[str]] = {}
    current: list[str] | None = None
    for line in text.splitlines():
        match = re.match(r"# (\S+\.yaml) \(beside \S+\)", line)
        if match:
            current = files.setdefault(home / match.group(1), [])
        elif current is not None:
            current.append(line)
    for path, lines in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines).strip() + "\n")
    return next(p for p in files if p.parent == home)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["drift", "angle-dependent gain"])
def test_printed_suggestions_load_and_carry_units(case, tmp_path) -> None:
    """Every printed suggestion, written literally as the comments say, loads and solves;
    coefficients carry the units of what they multiply; terms go into the error `e`."""
    shutil.copytree(ROOT / "models", tmp_path / "models")
    shutil.copytree(PROBLEMS, tmp_path / "problems")
    home = tmp_path / "problems"
    scenario = _scenario(CASES[case][0])
    data = _data(scenario, seed=64)
    diag = diagnose(symcal.solve(home / "platen_self_calibration_implicit.yaml", data))
    assert diag.significant
    for cand in diag.significant[:3]:
        text = diag.yaml[cand.label]
        overlay = _apply_printed(text, home)
        again = symcal.solve(overlay, data)
        assert again.success
        assert "  e: base.e + " in text
    lead = diag.yaml[diag.significant[0].label]
    unit = {"drift": "mm/s", "angle-dependent gain": "mm/rad"}[case]
    assert f"unit: {unit}" in lead


@pytest.mark.slow
def test_symcal_improve_json_and_files(tmp_path, capsys) -> None:
    """`symcal improve --json` prints the documented shape; every revision and the final
    problem are overlays that load; the ladder is written."""
    scenario = _scenario(CASES["drift"][0])
    paths = {}
    from symcal.data.dataset import write_table

    for name, ds in _data(scenario, seed=65).items():
        paths[name] = write_table(tmp_path / f"{name}.csv", dict(ds.columns)) or \
            tmp_path / f"{name}.csv"
    out = tmp_path / "out"
    code = main(["improve", str(IMPLICIT), "--data", f"calibration={paths['calibration']}",
                 "--data", f"flyby={paths['flyby']}", "--out", str(out), "--json", "--quiet"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["quiet"] is True
    assert doc["rounds"][0]["added"] is None
    assert doc["rounds"][0]["problem"] == str(IMPLICIT)
    assert doc["rounds"][1]["added"] == "s1.p_hat += a slow drift in time (t)"
    for r in doc["rounds"]:
        assert {"added", "problem", "statistics", "significant"} <= set(r)
        assert symcal.load_problem(r["problem"])
    assert doc["rounds"][-1]["significant"] == 0
    final = symcal.load_problem(doc["final_problem"])
    assert "s1.drift_t" in final.parameter_names
    # the final problem is solved on the data the loop was given, not the problem's own
    assert {n: (d.path, d.role) for n, d in final.datasets.items()} == {
        "calibration": (paths["calibration"].resolve(), "fit"),
        "flyby": (paths["flyby"].resolve(), "check")}
    again = symcal.solve(final)
    last = symcal.solve(doc["rounds"][-1]["problem"],
                        data={n: str(p) for n, p in paths.items()})
    assert np.array_equal(again.theta, last.theta)
    for name in ("ladder.txt", "ladder.json", "ladder.png"):
        assert (out / name).exists()


DUAL = PROBLEMS / "dual_sensor_calibration.yaml"
DUAL_IMPLICIT = PROBLEMS / "dual_sensor_calibration_implicit.yaml"


def _dual(gain_y: float = 0.0):
    """courier_dual_clean.yaml, the coordination sensor's y channel with a gain error."""
    if not gain_y:
        return courier_scenarios.dual()
    return courier_scenarios.dual(courier_scenarios.psd(y={"g": gain_y}))


@pytest.mark.slow
def test_dual_clean_data_is_one_switch_from_quiet() -> None:
    """The dual problem on clean data: explicit, the approximation leads, asking for 1 ×
    the implicit problem within 3 standard errors; the implicit problem is quiet."""
    data = _data(_dual(), seed=66)
    first = diagnose(symcal.solve(DUAL, data))
    lead = first.significant[0]
    assert lead.label == symcal.revise.diagnose.APPROXIMATION
    assert abs(lead.coefficient[0] - 1) < 3 * lead.coefficient_se[0]
    assert "extends: dual_sensor_calibration_implicit.yaml" in first.yaml[lead.label]
    assert not diagnose(symcal.solve(DUAL_IMPLICIT, data)).significant


@pytest.mark.slow
def test_coordination_gain_is_named_by_its_channels_and_fixed(tmp_path) -> None:
    """A 2 % gain error in the coordination sensor's y channel: to these constraints it is
    the same as an x-channel gain (h scales both), so the group says the channels
    disagree in gain; the true term is in it, and one revision reaches the floor."""
    scenario = _dual(gain_y=0.02)
    data = _data(scenario, seed=67)
    diag = diagnose(symcal.solve(DUAL_IMPLICIT, data))
    lead = diag.significant[0]
    assert "cs.c_y += a term linear in psi_y" in (lead.label, *lead.indistinguishable)
    assert lead.basis.kind == "linear" and lead.output.startswith("cs.")
    assert "the c_x and c_y channels of cs disagree in gain" in diag.candidate_text(lead)
    from symcal.revise.effects import revised_problem

    again = symcal.solve(revised_problem(diag.result.problem, lead, tmp_path), data)
    floors = courier_scenarios.floors(again.problem, scenario)
    dof = np.sqrt(again.uncertainty.dof / again.rows)
    for name in ("g_x", "g_y", "g_p"):
        assert again.stat(name, unit="mm").after.std < 1.10 * floors[f"{name}_std"] * dof, name


def _assert_dual_at_floor(result: symcal.Result, scenario) -> None:
    """g_x, g_y and g_p within 10 % of their noise floors on every dataset (on the
    calibration data allowing for the degrees of freedom the fit used)."""
    floors = courier_scenarios.floors(result.problem, scenario)
    dof = np.sqrt(result.uncertainty.dof / result.rows)
    for s in result.statistics:
        if s.name in ("g_x", "g_y", "g_p"):
            floor = floors[f"{s.name}_std"] * (dof if s.dataset == "calibration" else 1)
            assert s.after.std < 1.10 * floor, (s.name, s.dataset)


@pytest.mark.slow
def test_improve_fixes_the_coordination_gain_and_ends_quiet(tmp_path) -> None:
    """The 2 % y-channel gain, through `improve`: one round, at the floor on the
    calibration and the fly-by, the coefficient (-h·g: the model corrects the reading)
    within 3 standard errors; what stays significant is aliased with l_x (its standard
    error would grow many times) and is reported apart, so the loop ends quiet."""
    scenario = _dual(gain_y=0.02)
    data = _data(scenario, seed=67)
    result = improve(DUAL_IMPLICIT, tmp_path / "out", data, max_rounds=3)
    assert [r.added for r in result.rounds] == [None, "cs.c_y += a term linear in psi_y"]
    assert result.quiet
    assert all(why.startswith("it is nearly aliased with the parameters already there: "
                              "the standard error of l_x grows")
               for _, why in result.aliased)
    assert {a["label"] for a in result.to_dict()["aliased"]} == {
        label for label, _ in result.aliased}
    final = result.rounds[-1].result
    _assert_dual_at_floor(final, scenario)
    gain = next(p for p in final.params.values() if p.name == "cs.lin_psi_y")
    assert abs(gain.value - (-50.0 * 0.02)) < 3 * gain.se


@pytest.mark.slow
def test_improve_never_replaces_a_file_it_did_not_write(tmp_path, capsys) -> None:
    """A user's own file in --out is refused before any work and left as it was; a folder
    symcal wrote can be used again."""
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "final.yaml"
    mine.write_text("my notes\n")
    code = main(["improve", str(IMPLICIT), "--out", str(out), "--quiet"])
    assert code == 2
    assert "--out " + str(out) in capsys.readouterr().err
    assert mine.read_text() == "my notes\n"
    mine.unlink()
    assert main(["improve", str(IMPLICIT), "--out", str(out), "--quiet", "--max-rounds",
                 "1"]) in (0, 1)
    assert main(["improve", str(IMPLICIT), "--out", str(out), "--quiet", "--max-rounds",
                 "1"]) in (0, 1)
    capsys.readouterr()


def test_a_new_run_removes_the_previous_runs_files_only(tmp_path) -> None:
    """Run again into the same --out, improve leaves no file of the previous run that
    the new one does not write (an interrupted or shorter run left an old round extending
    a new one), and never a file symcal did not write or that was changed since."""
    hidden = ROOT / "examples" / "hidden_effect" / "problem.yaml"
    out = tmp_path / "out"
    first = improve(hidden, out)
    assert [r.problem_file.name for r in first.rounds[1:]] == ["problem_round1.yaml"]
    models = sorted(p.name for p in (out / "models").glob("*.yaml"))
    assert models == ["platen_segment_p_hat_h3_p.yaml"]
    (out / "notes.yaml").write_text("mine: true\n")
    (out / "problem_round7.yaml").write_text("problem: mine\n")   # not symcal's
    # an interrupted run's trials of a round's other leads
    for stem in ("problem_round1_alt0", "problem_round1_alt1_try2", "problem_round2_all"):
        write_output(out / f"{stem}.yaml", f"problem: {stem}\n")
    lines: list[str] = []
    second = improve(hidden, out, max_rounds=0, progress=lines.append)
    assert len(second.rounds) == 1
    assert lines[0] == f"removed the previous run's 6 file(s) from {out}"
    left = sorted(p.relative_to(out).as_posix() for p in out.rglob("*")
                  if p.is_file() and not p.name.startswith("."))
    assert left == ["final.yaml", "notes.yaml", "problem_round7.yaml"]
    assert (out / "notes.yaml").read_text() == "mine: true\n"


NO_LATERAL = """problem: dual_no_lateral
extends: {root}/problems/dual_sensor_calibration_implicit.yaml
doc: the implicit dual problem without the lateral terms of eq. (9)
instances:
  s1: {{model: {root}/models/platen_segment_implicit.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s2.p, s2.u, s4.p, s4.u]}}}}
  s2: {{model: {root}/models/platen_segment_implicit.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s1.p, s1.u, s3.p, s3.u]}}}}
  s3: {{model: {root}/models/platen_segment_implicit.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s2.p, s2.u, s4.p, s4.u]}}}}
  s4: {{model: {root}/models/platen_segment_implicit.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s1.p, s1.u, s3.p, s3.u]}}}}
expressions: {{tx: null, ty: null, tt: null}}
implicit: null
"""
NO_LATERAL_EXPLICIT = """problem: dual_no_lateral_explicit
extends: {root}/problems/dual_sensor_calibration.yaml
doc: the dual problem without the lateral terms of eq. (9)
instances:
  s1: {{model: {root}/models/platen_segment.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s2.p, s2.u, s4.p, s4.u]}}}}
  s2: {{model: {root}/models/platen_segment.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s1.p, s1.u, s3.p, s3.u]}}}}
  s3: {{model: {root}/models/platen_segment.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s2.p, s2.u, s4.p, s4.u]}}}}
  s4: {{model: {root}/models/platen_segment.yaml, inputs: {{q: null}},
       candidates: {{variables: [p, u, t, theta_raw, s1.p, s1.u, s3.p, s3.u]}}}}
"""


@pytest.mark.slow
@pytest.mark.parametrize(("start", "seed"), [("implicit", 8), ("implicit", 5),
                                             ("explicit", 8)])
def test_lateral_dependence_in_the_dual_problem_is_found_and_fixed(start, seed,
                                                                    tmp_path) -> None:
    """The dual problem without eq. (9), on data with the lateral terms of every segment:
    the same effect shows in the four sibling segments, so a round adds it to each that
    shows it (its harmonic of the perpendicular pair's reading; starting explicit, the
    model's own approximation first); quiet at the floor on the calibration and the
    fly-by in 3 rounds at most (issue 23's acceptance; a sibling whose term leads another
    instance's group waits for the next round), each coefficient within 3 standard errors
    of eq. (9)."""
    first = tmp_path / "no_lateral.yaml"
    text = NO_LATERAL if start == "implicit" else NO_LATERAL_EXPLICIT
    first.write_text(text.format(root=ROOT.as_posix()))
    scenario = load_scenario(PROBLEMS / "scenarios" / "courier_dual_clean.yaml")
    data = _data(scenario, seed=seed)
    result = improve(first, tmp_path / "out", data, max_rounds=3)
    assert result.quiet and len(result.rounds) - 1 <= 3, [r.added for r in result.rounds]
    added = " ".join(r.added or "" for r in result.rounds)
    for term in ("s1.p_hat += harmonic 1 of s4.u", "s2.p_hat += harmonic 1 of s1.u",
                 "s3.p_hat += harmonic 1 of s2.u", "s4.p_hat += harmonic 1 of s3.u"):
        assert term in added
    final = result.rounds[-1].result
    _assert_dual_at_floor(final, scenario)
    lateral = symcal.simulation.truth(scenario)["effects"]["lateral"]["values"]
    params = dict(final.params)
    for i, other in enumerate(("s4", "s1", "s2", "s3")):
        for name, value in ((f"s{i + 1}.h1_sin_{other}_u", lateral[f"s{i + 1}.k9"]),
                            (f"s{i + 1}.h1_cos_{other}_u", lateral[f"s{i + 1}.k10"])):
            assert abs(params[name].value - value) < 3 * params[name].se, name


def test_improve_says_what_is_left_where_it_ends_above_the_floor(tmp_path) -> None:
    # stopped before its round: above the floor, the harmonic of s2 left in g_p
    hidden = ROOT / "examples" / "hidden_effect" / "problem.yaml"
    from symcal.cli.improve import _left
    from symcal.report.text import left_lines

    outcome = improve(hidden, tmp_path / "again", max_rounds=0)
    last = outcome.rounds[-1].result
    assert not outcome.quiet and last.at_floor is False
    left, hints = _left(outcome, 0.01)
    diag = diagnose(last, 0.01)
    assert left and left == left_lines(diag)
    assert hints == diag.unsearched
    assert left[0].startswith("calibration g_p: ") and " along " in left[0]


def test_the_models_approximation_is_solved_whatever_its_prediction() -> None:
    # the dual courier with a 1 ms latency (acceptance, seed 1000): the approximation,
    # predicted +0.3 %, was left unsolved, and it paid; a term predicted so is not solved
    from symcal.revise.diagnose import APPROXIMATION
    from symcal.revise.improve import _predicted_worse

    diag = diagnose(symcal.solve(EXPLICIT), report=False)
    by_label = {c.label: c for c in diag.candidates}
    term = next(c for c in diag.candidates if c.basis.kind == "harmonic" and c.reduction)
    for cand in (by_label[APPROXIMATION], term):
        cand.reduction = {k: (now, 2 * now) for k, (now, _) in cand.reduction.items()}
        cand.scatter = {k: (now, 3 * now) for k, (now, _) in cand.scatter.items()}
    assert _predicted_worse(diag, [APPROXIMATION]) is None
    assert _predicted_worse(diag, [term.label]) == (
        "not solved: the diagnosis predicts that the held-out constraint residuals do not "
        "fall (mean change +100.0% in RMS, +200.0% in standard deviation)")
    # its scatter falls: that is not enough where its mean grows the RMS by far (a
    # reviewer's case: +30 % in RMS kept for -0.1 % in standard deviation) ...
    term.scatter = {k: (now, 0.999 * now) for k, (now, _) in term.scatter.items()}
    term.reduction = {k: (now, 1.3 * now) for k, (now, _) in term.reduction.items()}
    assert _predicted_worse(diag, [term.label]).startswith(
        "not solved: the diagnosis predicts that the held-out constraint residuals do not "
        "fall (mean change +30.0% in RMS, -0.1% in standard deviation)")
    # ... and is where the RMS grows by less than the slack beyond the margin (+0.5 %)
    term.reduction = {k: (now, 1.004 * now) for k, (now, _) in term.reduction.items()}
    assert _predicted_worse(diag, [term.label]) is None


@pytest.mark.parametrize("corr", [0.0, 0.6, -0.95])
def test_the_wald_test_holds_for_coefficients_of_very_different_sizes(corr) -> None:
    # a new user's turbine meter: a quadratic's two coefficients with variances 1.2e-9 and
    # 3.8e-27 (their own units); pinv of that covariance dropped the smaller direction and
    # gave χ² 0.0396 for a term 15 standard errors from zero
    from types import SimpleNamespace

    import scipy.stats

    from symcal.revise.watch import wald

    se = np.array([np.sqrt(1.2e-9), np.sqrt(3.8e-27)])
    cov = np.array([[1.0, corr], [corr, 1.0]]) * np.outer(se, se)
    value = np.array([0.3 * se[0], -15.3 * se[1]])
    names = ["tur.lin_q_t", "tur.quad_q_t"]
    result = SimpleNamespace(
        uncertainty=SimpleNamespace(names=["tur.k", *names],
                                    covariance=np.block([[np.eye(1), np.zeros((1, 2))],
                                                         [np.zeros((2, 1)), cov]])),
        params={n: SimpleNamespace(value=v) for n, v in zip(names, value, strict=True)})
    z = value / se                                  # the same test in standard units
    expected = float(z @ np.linalg.solve(np.array([[1.0, corr], [corr, 1.0]]), z))
    chi2, p = wald(result, names)
    assert chi2 == pytest.approx(expected, rel=1e-9) and expected > 200
    assert p == pytest.approx(scipy.stats.chi2.sf(expected, 2), rel=1e-6)


@pytest.mark.slow
def test_each_refusal_says_its_round(tmp_path, capsys) -> None:
    """A candidate refused in one round may be tried and refused again in the next: each
    "not kept" line and JSON entry says which round (a new user read the same label
    twice, with different numbers, as a duplicate)."""
    out = tmp_path / "out"
    code = main(["improve", str(DUAL_IMPLICIT), "--out", str(out), "--json", "--quiet"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 1
    kept = len(doc["rounds"]) - 1
    rounds = [r["round"] for r in doc["rejected"]]
    assert rounds and rounds == sorted(rounds)
    assert set(rounds) <= set(range(1, kept + 2)) and rounds[-1] == kept + 1
    assert main(["improve", str(DUAL_IMPLICIT), "--out", str(tmp_path / "b"), "--quiet"]) == 1
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "not kept" in ln]
    assert [int(ln.split("(round ")[1].split(")")[0]) for ln in lines] == rounds
