"""Reports a person reads at a glance: unit symbols, display units on axes, the verdict,
regressions flagged, noise floors, revisions labelled by file, no self-referential
finding (symcal.report.text, symcal.report.plots, symcal.report.html, symcal.revise.ladder,
symcal.base.units)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ROOT, courier_data

import symcal
from symcal.base.units import axis_unit, symbol
from symcal.calibrate.result import REGRESSION_TOLERANCE, Regression, regressions
from symcal.data.dataset import make_dataset
from symcal.experiment.predict import noise_floors as propagated_floors
from symcal.report import plots
from symcal.report.html import html_report
from symcal.report.ladder import ladder_report, save_ladder_plot
from symcal.report.text import (
    diagnosis_document,
    diagnosis_report,
    diagnosis_verdict,
    json_report,
    noise_floors,
    self_referential,
    text_report,
    verdict_lines,
)
from symcal.revise.diagnose import diagnose
from symcal.revise.ladder import compare, revision_labels
from symcal.simulation import load_scenario

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
SCENARIOS = ROOT / "problems" / "scenarios"
ASCII_MICRO = re.compile(r"\bu(m|rad)\b")       # "um", "urad" as words


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _variant(folder: Path, scenario: str, name: str = "platen_self_calibration") -> Path:
    """The bundled §3.1 problem on data simulated from ``scenario`` (a file in folder)."""
    return _write(folder / "problem.yaml", f"""\
problem: {name}
extends: {PLATEN}
datasets:
  calibration: {{simulate: {scenario}, run: calibration, seed: 1}}
  flyby: {{simulate: {scenario}, run: flyby, seed: 1}}
""")


@pytest.fixture(scope="module")
def gain(tmp_path_factory) -> symcal.Result:
    """Clean courier but for an angle-dependent gain in segment 2 (6 mm/rad): the
    calibration absorbs it into s2's tooth error and the fly-by position gets worse."""
    folder = tmp_path_factory.mktemp("gain")
    _write(folder / "scenario.yaml", f"""\
scenario: courier_platen_angle_gain
extends: {SCENARIOS / "courier_platen_clean.yaml"}
effects:
  angle_s2:
    values: {{s2.a: 6.0}}
    add: {{e2: ang*s2.a}}
""")
    return symcal.solve(_variant(folder, "scenario.yaml", "platen_angle_gain"))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> symcal.Result:
    """The bundled problem on the clean courier (the model is the truth but for noise)."""
    folder = tmp_path_factory.mktemp("clean")
    return symcal.solve(_variant(folder, str(SCENARIOS / "courier_platen_clean.yaml")))


@pytest.fixture(scope="module")
def gain_diagnosis(gain: symcal.Result):
    return diagnose(gain)


# ----------------------------------------------------------------------------- units


def test_symbols_and_axis_units() -> None:
    assert [symbol(u) for u in ("um", "urad", "", None, "(internal)", "mm", "mrad", "µm")] \
        == ["µm", "µrad", "(internal)", "(internal)", "(internal)", "mm", "mrad", "µm"]
    # any unit pint knows is drawn as declared (furlong is a length); a non-unit unscaled
    assert [axis_unit(u) for u in ("rad", "mrad", "urad", "um", "mm", "s", "", "furlong",
                                   "mmm")] \
        == ["mrad", "mrad", "urad", "um", "mm", "s", "", "furlong", ""]


# ----------------------------------------------------------------------------- regressions


def test_regression_flagged_in_result_text_and_json(gain: symcal.Result) -> None:
    (reg,) = gain.regressions
    stats = gain.stat("position_y", "flyby")
    assert (reg.dataset, reg.name, reg.kind, reg.measure, reg.unit) == (
        "flyby", "position_y", "comparison", "std", "um")
    assert stats.unit == "um"                          # the values are in the unit stated
    assert reg.before == pytest.approx(stats.before.std)
    assert reg.after == pytest.approx(stats.after.std)
    assert 7 < reg.before < 9 and reg.after > 2 * reg.before

    text = text_report(gain)
    line = (f"calibration made flyby position_y vs reference worse: std {reg.before:.4g} → "
            f"{reg.after:.4g} µm")
    verdict = text.split("\n\n")[1].splitlines()
    assert verdict[0] == "Verdict"
    assert verdict[1] == "  solved: 1 stage converged (linear)"
    assert verdict[3] == "  " + line
    assert verdict[4] == ("  3 parameter direction(s) the data cannot determine (their "
                          "initial values are kept; see Identifiability)")
    row = next(ln for ln in text.splitlines()
               if "position_y vs reference" in ln and "(arbitrary zero)" in ln)
    assert row.rstrip().endswith("WORSE")
    assert sum("WORSE" in ln for ln in text.splitlines()) == 1

    doc = json.loads(json_report(gain))
    assert doc["regressions"] == [{
        "dataset": "flyby", "name": "position_y", "kind": "comparison", "measure": "std",
        "before": pytest.approx(reg.before), "after": pytest.approx(reg.after),
        "ratio": pytest.approx(reg.after / reg.before), "unit": "um"}]


def test_regressions_survive_save_and_load(gain: symcal.Result, tmp_path: Path) -> None:
    loaded = symcal.Result.load(gain.save(tmp_path / "result.json"))
    assert [(r.dataset, r.name) for r in loaded.regressions] == [("flyby", "position_y")]
    assert loaded.to_dict()["regressions"] == [
        {k: pytest.approx(v) if isinstance(v, float) else v for k, v in r.items()}
        for r in gain.to_dict()["regressions"]]


def test_no_regression_on_clean_data(clean: symcal.Result) -> None:
    assert clean.regressions == ()
    text = text_report(clean)
    assert (f"  no residual or comparison is worse after calibration (by more than "
            f"{REGRESSION_TOLERANCE:.0%})") in text
    assert "WORSE" not in text and " worse: " not in text
    assert json.loads(json_report(clean))["regressions"] == []


def test_what_counts_as_worse() -> None:
    """std for a comparison whose mean is arbitrary, RMS otherwise; 20 % tolerance."""
    from symcal.analysis.fit import SeriesStats, Spread

    def stats(name, before, after, remove_mean):
        return SeriesStats(name, "comparison" if remove_mean else "constraint", "d", "um",
                           10, Spread(*before), Spread(*after), remove_mean)

    found = regressions((
        stats("offset", (1e-3, 0.0, 1e-3), (3e-3, 2.9e-3, 0.5e-3), False),  # rms 1 → 3 µm
        stats("mean_only", (1e-3, 0.0, 1e-3), (3e-3, 2.9e-3, 0.5e-3), True),  # std falls
        stats("noise", (1e-3, 0.0, 1e-3), (1.15e-3, 0.0, 1.15e-3), True),   # +15 %: noise
        stats("spread", (1e-3, 0.0, 1e-3), (1.3e-3, 0.0, 1.3e-3), True)))   # +30 %
    assert found == (Regression("d", "offset", "constraint", "rms", pytest.approx(1.0),
                                pytest.approx(3.0), "um"),
                     Regression("d", "spread", "comparison", "std", pytest.approx(1.0),
                                pytest.approx(1.3), "um"))


# ----------------------------------------------------------------------------- noise floors


def _floor(result: symcal.Result, run: str) -> float:
    """g_p's floor on ``run``: the noise of the scenario the data were simulated from,
    propagated through the problem at its truth."""
    scenario = load_scenario(result.problem.datasets[run].scenario)
    return propagated_floors(result.problem, scenario, run)["g_p_std"]


def test_noise_floor_column_equals_the_simulators_floor(clean: symcal.Result) -> None:
    floors = {d: _floor(clean, d) for d in ("calibration", "flyby")}
    assert noise_floors(clean) == {("calibration", "g_p"): floors["calibration"],
                                   ("flyby", "g_p"): floors["flyby"]}
    s = np.sqrt(0.0005**2 + 0.0002**2 / 12)    # the noise of one reading
    for floor in floors.values():
        # 2 s through the slope of the calibrated errors: g_p sums (1 + e'(p)) dp of four
        # readings, e' up to about 0.15 here, which raises 2 s by 1 % on the scatter and
        # 4 % on the fly-by (where s1 and s3 keep one tooth phase)
        assert 1.005 * 2 * s < floor < 1.06 * 2 * s
    text = text_report(clean)
    lines = text.splitlines()
    header = next(ln for ln in lines if ln.lstrip().startswith("dataset"))
    assert header.rstrip().endswith("unit  noise floor  std/floor")
    for dataset in ("calibration", "flyby"):
        after = clean.stat("g_p", dataset).shown("after").std
        floor = floors[dataset]
        row = next(ln for ln in lines if ln.split()[:2] == [dataset, "g_p"])
        assert row.split()[-3:] == ["µm", f"{floor / 1e-3:.4g}", f"{after / (floor / 1e-3):.3g}"]
    # comparisons have no floor the simulator states: their cells stay blank
    theta = next(ln for ln in lines if "theta_x vs reference" in ln)
    assert theta.rstrip().endswith("mrad")
    worst = max((clean.stat("g_p", d, unit="mm") for d in ("calibration", "flyby")),
                key=lambda s: s.after.std / floors[s.dataset])
    floor = floors[worst.dataset]
    assert (f"  worst against its noise floor: {worst.dataset} g_p std "
            f"{worst.after.std / 1e-3:.4g} µm = {worst.after.std / floor:.2f} × the floor "
            f"{floor / 1e-3:.4g} µm") in text


def test_floor_unknown_for_data_not_simulated_from_the_scenario(true_k) -> None:
    data = {"calibration": make_dataset("calibration", "file",
                                        courier_data(300, true_k, 5e-4, 3), []),
            "flyby": make_dataset("flyby", "file", courier_data(200, true_k, 5e-4, 4), [])}
    result = symcal.solve(PLATEN, data)
    assert noise_floors(result) == {}
    text = text_report(result)
    assert "  noise floors unknown (the data were not simulated from a scenario)" in text
    header = next(ln for ln in text.splitlines() if ln.lstrip().startswith("dataset"))
    assert "noise floor" not in header          # no column of blanks


def test_bundled_report_uses_symbols() -> None:
    result = symcal.solve(PLATEN)
    text = text_report(result)
    assert "µm" in text and "mrad" in text
    assert not ASCII_MICRO.search(text), ASCII_MICRO.search(text)
    assert verdict_lines(result)[0] == "solved: 1 stage converged (linear)"
    # the JSON keeps the declared unit strings
    doc = json.loads(json_report(result))
    assert {s["unit"] for s in doc["statistics"]} == {"um", "mrad"}


# ----------------------------------------------------------------------------- diagnosis


def _candidate(label: str) -> SimpleNamespace:
    return SimpleNamespace(label=label)


def _fake_diagnosis(result: symcal.Result, significant=(), **more) -> SimpleNamespace:
    return SimpleNamespace(result=result, significant=tuple(significant),
                           candidate_text=lambda c: f"text of {c.label}", **more)


def test_diagnosis_verdict_before_and_after_uncalibratable(gain: symcal.Result) -> None:
    reg = gain.regressions[0]
    g_p = gain.stat("g_p", "calibration", unit="mm")
    floor = _floor(gain, "calibration")
    where = [f"where it fails: calibration g_p std {g_p.after.std / 1e-3:.4g} µm is "
             f"{g_p.after.std / floor:.2f} × its noise floor",
             f"calibration made flyby position_y vs reference worse: std {reg.before:.4g} → "
             f"{reg.after:.4g} µm"]
    old = _fake_diagnosis(gain, [_candidate("s2.p_hat += a term linear in theta_raw"),
                                 _candidate("s1.p_hat += harmonic 3 of s1.p")])
    assert diagnosis_verdict(old) == [
        "solved: 1 stage converged (linear)", *where,
        "what to add: s2.p_hat += a term linear in theta_raw (and 1 more significant, below)",
        "what cannot be calibrated: 3 parameter direction(s) the data cannot determine"]
    new = _fake_diagnosis(gain, uncalibratable=(_candidate("s1.p_hat += harmonic 1 of s4.p"),))
    assert diagnosis_verdict(new)[-2:] == [
        "what to add: nothing significant (no candidate effect passes the test)",
        "what cannot be calibrated: s1.p_hat += harmonic 1 of s4.p (real, but these "
        "constraints cannot determine it); 3 parameter direction(s) the data cannot "
        "determine"]


def test_diagnosis_report_flags_the_regression(gain: symcal.Result, gain_diagnosis) -> None:
    text = diagnosis_report(gain_diagnosis)
    reg = gain.regressions[0]
    line = (f"calibration made flyby position_y vs reference worse: std {reg.before:.4g} → "
            f"{reg.after:.4g} µm")
    head = text.split("\n\n")[1].splitlines()
    assert head[0] == "Verdict"
    assert head[1:] == [f"  {ln}" for ln in diagnosis_verdict(gain_diagnosis)]
    assert f"  {line}" in head
    assert f"  {line} ({reg.ratio:.2f} ×)" in text.split("Worse after calibration")[1]
    floor = _floor(gain, "flyby")
    std = float(np.std(next(v for v in gain_diagnosis.residuals
                             if (v.dataset, v.name) == ("flyby", "g_p")).after)) / 1e-3
    assert (f"  flyby g_p: std {std:.4g} µm (noise floor {floor / 1e-3:.4g} µm; "
            f"{std / (floor / 1e-3):.2f} ×)") in text
    assert not ASCII_MICRO.search(text)


def test_diagnosis_document(gain: symcal.Result, gain_diagnosis) -> None:
    doc = diagnosis_document(gain_diagnosis, series=True)
    json.dumps(doc)
    assert [(r["dataset"], r["name"]) for r in doc["regressions"]] == [("flyby", "position_y")]
    assert doc["verdict"] == diagnosis_verdict(gain_diagnosis)
    rows = {(r["dataset"], r["name"]): r for r in doc["residuals"]}
    floor = _floor(gain, "flyby")
    assert rows[("flyby", "g_p")]["noise_floor"] == pytest.approx(floor / 1e-3)
    assert rows[("flyby", "position_y")]["noise_floor"] is None
    assert rows[("flyby", "position_y")]["contains"] == ["p_y", "position_y"]
    assert rows[("flyby", "theta_x")]["contains"] == ["theta_x"]
    units = {b["variable"]: b["unit"] for r in doc["residuals"] for b in r["binned"]}
    assert units.get("theta_x", "mrad") == "mrad"
    assert all(u == "mm" for v, u in units.items() if v.startswith("phase of s"))
    assert rows[("flyby", "g_p")]["series"]["x"]["unit"] == "mm"


def test_self_referential_finding_absent() -> None:
    """On the bundled problem the fly-by's θx error is binned against θx itself (its
    estimate ≈ a constant plus the error): no report or figure may say it varies with it."""
    result = symcal.solve(PLATEN)
    diag = diagnose(result)
    assert self_referential(result)["theta_x"] == frozenset({"theta_x"})
    assert self_referential(result)["position_y"] == frozenset({"position_y", "p_y"})
    view = next(v for v in diag.residuals if (v.dataset, v.name) == ("flyby", "theta_x"))
    assert "theta_x" in [b.variable for b in view.binned]       # the raw structure has it
    text = diagnosis_report(diag)
    block = text.split("  flyby theta_x vs reference:")[1].split("\n  flyby")[0]
    assert "varies with" in block and "varies with theta_x:" not in block
    for name in ("theta_x", "theta_y"):
        block = text.split(f"  flyby {name} vs reference:")[1].split("\n  ")[0]
        assert f"varies with {name}:" not in block
    doc = diagnosis_document(diag, series=True)
    fig = plots.build_figure(doc, "structure")
    labels = {ax.get_title(): ax.get_xlabel() for ax in fig.axes if ax.get_visible()}
    assert not labels["flyby/theta_x (η² = {:.2f})".format(
        next(b.eta2 for b in view.binned if b.variable != "theta_x"))].startswith("theta_x")
    # even from a document without "contains": by the residual's own name
    for row in doc["residuals"]:
        row.pop("contains")
    fig = plots.build_figure(doc, "structure")
    assert all(not (ax.get_title().startswith("flyby/theta_x")
                    and ax.get_xlabel().startswith("theta_x ")) for ax in fig.axes)


# ----------------------------------------------------------------------------- figures


def _figure_texts(fig) -> list[str]:
    texts = [t.get_text() for t in fig.findobj(lambda o: hasattr(o, "get_text"))]
    return [t for t in texts if t]


@pytest.mark.slow
def test_angle_axes_in_mrad_without_crowded_ticks(gain_diagnosis) -> None:
    doc = diagnosis_document(gain_diagnosis, series=True)
    fig = plots.build_figure(doc, "structure")
    rows = [r for r in doc["residuals"] if plots._findings(r)]
    angle_axes = 0
    for ax, row in zip([a for a in fig.axes if a.get_visible()], rows, strict=True):
        top = plots._findings(row)[0]
        line = ax.containers[0][0]                          # the errorbar's data line
        if top["unit"] in ("rad", "mrad"):
            angle_axes += 1
            assert ax.get_xlabel() == f"{top['variable']} [mrad]"
            np.testing.assert_allclose(line.get_xdata(), np.array(top["centers"]) / 1e-3)
        fig.canvas.draw()
        low, high = sorted(ax.get_xlim())
        shown = [t for t in ax.get_xticklabels()
                 if t.get_text() and low <= t.get_position()[0] <= high]
        assert len(shown) <= plots.MAX_X_TICKS + 1
        boxes = [t.get_window_extent() for t in shown]
        assert all(a.x1 <= b.x0 for a, b in zip(boxes, boxes[1:], strict=False)), \
            ax.get_xlabel()
    assert angle_axes >= 2
    for name in plots.figure_names(doc):
        texts = _figure_texts(plots.build_figure(doc, name))
        assert not [t for t in texts if ASCII_MICRO.search(t)], name
    ref = plots.build_figure(doc, "reference_flyby")
    legend = [t.get_text() for t in ref.axes[0].get_legend().get_texts()]
    assert legend[1].endswith("µm; worse than before)")


# ----------------------------------------------------------------------------- HTML


@pytest.mark.slow
def test_html_verdict_floors_and_regressions(gain: symcal.Result, gain_diagnosis) -> None:
    doc = diagnosis_document(gain_diagnosis, series=False)
    text = text_report(gain) + "\n" + diagnosis_report(gain_diagnosis)
    page = html_report(doc, text)
    verdict = page.split('<section class="verdict">')[1].split("</section>")[0]
    assert verdict.count("<li") == len(doc["verdict"])
    reg = gain.regressions[0]
    assert (f'<li class="bad">calibration made flyby position_y vs reference worse: std '
            f"{reg.before:.4g} → {reg.after:.4g} µm</li>") in verdict
    assert page.index('<section class="verdict">') < page.index("<h2>Residuals</h2>")
    assert '<tr class="worse"><td>flyby</td><td>position_y</td>' in page
    assert "<th>noise floor</th><th>std/floor</th>" in page
    assert "<td>µm</td>" in page and "<td>um</td>" not in page
    assert not ASCII_MICRO.search(page.split("<h2>Text report</h2>")[0])
    # without a verdict in the document: the last Verdict block of the text
    bare = {k: v for k, v in doc.items() if k != "verdict"}
    assert html_report(bare, text) == page
    assert "<li>given</li>" in html_report(bare, text, verdict=["given"])


# ----------------------------------------------------------------------------- compare


def test_revision_labels() -> None:
    assert revision_labels(["/w/a/x/problem.yaml", "/w/b/x/problem.yaml", "/w/q.yaml",
                            "/w/q.yaml", "/w/r.yaml", "/w/y/r.yaml"]) == [
        "a/x/problem.yaml", "b/x/problem.yaml", "q.yaml (1)", "q.yaml (2)", "w/r.yaml",
        "y/r.yaml"]
    assert revision_labels(["/w/problem.yaml", "/w/problem_revised.yaml"]) == [
        "problem.yaml", "problem_revised.yaml"]


def test_compare_labels_revisions_by_file(tmp_path: Path) -> None:
    """Two copies of a problem keep its name: the ladder tells them apart by file."""
    scenario = str(SCENARIOS / "courier_platen_clean.yaml")
    first = _variant(tmp_path / "first", scenario)
    second = _variant(tmp_path / "second", scenario)
    rungs = compare([symcal.solve(first), symcal.solve(second)])
    assert [r.name for r in rungs] == ["platen_self_calibration"] * 2
    assert [r.label for r in rungs] == ["first/problem.yaml", "second/problem.yaml"]
    text = ladder_report(rungs)
    header = text.splitlines()[2].split()
    assert header == ["first/problem.yaml", "second/problem.yaml"]
    assert "  calibration g_p std (µm)" in text and not ASCII_MICRO.search(text)
    doc = rungs[0].to_dict()
    assert (doc["name"], doc["label"]) == ("platen_self_calibration", "first/problem.yaml")
    assert doc["path"].endswith("first/problem.yaml")
    assert {s["unit"] for s in doc["spreads"]} == {"um", "mrad"}

    (png,) = save_ladder_plot(rungs, tmp_path / "plots")
    assert png.read_bytes().startswith(b"\x89PNG")
