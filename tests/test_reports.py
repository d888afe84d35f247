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

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
SCENARIOS = ROOT / "problems" / "scenarios"
ASCII_MICRO = re.compile(r"\bu(m|rad)\b")       # "um", "urad" as words


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _variant(folder: Path, scenario: str, name: str = "platen_self_calibration",
             more: str = "") -> Path:
    """The bundled §3.1 problem on data simulated from ``scenario`` (a file in folder)."""
    return _write(folder / "problem.yaml", f"""\
problem: {name}
extends: {PLATEN}
datasets:
  calibration: {{simulate: {scenario}, run: calibration, seed: 1}}
  flyby: {{simulate: {scenario}, run: flyby, seed: 1}}
{more}""")


def _series(result: symcal.Result, name: str, dataset: str | None = None):
    """A residual's statistics as stored (internal units, with its floor test)."""
    dataset = dataset or result.problem.fit_dataset
    return next(s for s in result.statistics if (s.name, s.dataset) == (name, dataset))


@pytest.fixture(scope="module")
def gain(tmp_path_factory) -> symcal.Result:
    """Clean courier but for an angle-dependent gain in segment 2 (6 mm/rad): with the
    paper's equal weights the calibration absorbs it into s2's tooth error and the fly-by
    position gets worse (8.1 → 18.8 µm; weighted by the propagated noise, the default, it
    gets better, 8.1 → 6.0 µm, and the fly-by angle θx 20 % worse)."""
    folder = tmp_path_factory.mktemp("gain")
    _write(folder / "scenario.yaml", f"""\
scenario: courier_platen_angle_gain
extends: {SCENARIOS / "courier_platen_clean.yaml"}
effects:
  angle_s2:
    values: {{s2.a: 6.0}}
    add: {{e2: ang*s2.a}}
""")
    return symcal.solve(_variant(folder, "scenario.yaml", "platen_angle_gain",
                                 "weighting: equal\n"))


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
    assert [ln.split(":")[0] for ln in verdict[2:4]] == ["  calibration", "  flyby"]
    at = verdict.index("  " + line)
    assert verdict[at + 1] == ("  3 parameter direction(s) the data cannot determine (their "
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
    assert (f"  no residual or comparison is worse after calibration by more than its noise "
            f"allows (by more than {REGRESSION_TOLERANCE:.0%} where its floor is unknown)") \
        in text
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


def test_floor_column_is_the_propagated_noise(clean: symcal.Result) -> None:
    """The floor of g_p is the readings' declared noise (0.503 µm) through g_p at the
    estimate: 2 σ times the RMS slope of the calibrated readings, within 1 % of the
    simulator's 2 σ (which takes the slope as 1); the report reads it from the result."""
    floors = noise_floors(clean)
    sim = 2 * np.sqrt(0.0005**2 + 0.0002**2 / 12)   # 0.5 µm noise, 0.2 µm steps, 2 readings
    assert set(floors) == {(d, n) for d in ("calibration", "flyby")
                           for n in ("g_p", "theta_x", "theta_y")} | {("flyby", "position_y")}
    for dataset in ("calibration", "flyby"):
        # measured: 0.7 % above on the scatter, 4 % on the fly-by, whose x segments sit
        # at one tooth phase each, where their calibrated slope 1 + e' is up to 1.1
        assert floors[(dataset, "g_p")] == pytest.approx(sim, rel=0.05)
        assert floors[(dataset, "g_p")] > sim        # the slope adds to the noise
    text = text_report(clean)
    lines = text.splitlines()
    header = next(ln for ln in lines if ln.lstrip().startswith("dataset"))
    assert header.rstrip().endswith("unit  noise floor  χ²/dof  95 % band  floor")
    # the explicit model cannot reach the floor on the clean courier (its error evaluated
    # at the raw reading leaves e'·e, scenario courier_platen_clean.yaml): above it on the
    # calibration scatter (χ²/dof 1.57), at it on the fly-by
    for dataset, mark in (("calibration", "ABOVE"), ("flyby", "at")):
        s = _series(clean, "g_p", dataset)
        row = next(ln for ln in lines if ln.split()[:2] == [dataset, "g_p"])
        lo, hi = s.noise.band
        assert row.split()[-5:] == ["µm", f"{s.floor / 1e-3:.4g}", f"{s.chi2_dof:.3g}",
                                    f"{lo:.2f}–{hi:.2f}", mark]
    # the verdict: the global test of every dataset, in the words
    cal, fly = clean.floor_tests
    assert (f"  calibration: {cal.ratio:.3g}× the noise floor (χ²/dof {cal.chi2_dof:.3g}, "
            f"band {cal.band[0]:.2f}–{cal.band[1]:.2f})") in text
    assert (f"  flyby: at the noise floor (χ²/dof {fly.chi2_dof:.3g}, band "
            f"{fly.band[0]:.2f}–{fly.band[1]:.2f})") in text
    assert clean.at_floor is False


def _bare_problem(folder: Path, time: bool) -> Path:
    """The §3.1 problem with models that declare no noise (columns without a preset)."""
    model = (ROOT / "models" / "platen_segment.yaml").read_text().replace(
        "    noise: 0.503 um   # 0.5 um reading noise and a 0.2 um quantization step "
        "(0.2/sqrt 12)\n", "")
    _write(folder / "seg.yaml", model)
    role = ", role: time" if time else ""
    text = PLATEN.read_text().replace("../models/platen_segment.yaml", "seg.yaml").replace(
        "columns: courier  # the courier data contract: t, p1..p4, psi_x, psi_y, x_ref, "
        "y_ref, theta_ref",
        f"columns:\n  t: {{unit: s{role}}}\n" + "".join(
            f"  {c}: {{unit: mm}}\n" for c in ("p1", "p2", "p3", "p4", "x_ref", "y_ref"))
        + "  theta_ref: {unit: rad}\n")
    return _write(folder / "bare.yaml", text)


def test_floor_unknown_without_declared_noise_and_estimated_on_time_ordered_rows(
        true_k, tmp_path) -> None:
    """Data from files, models without noise: the floor is unknown where the rows are
    not time-ordered, and estimated by successive differences where they are (the
    method named); with the bundled models' declared noise it is known whatever the data."""
    data = {"calibration": make_dataset("calibration", "file",
                                        courier_data(300, true_k, 5e-4, 3), []),
            "flyby": make_dataset("flyby", "file", courier_data(200, true_k, 5e-4, 4), [])}
    unknown = symcal.solve(_bare_problem(tmp_path / "a", time=False), data)
    assert unknown.problem.weighting == "equal"
    assert noise_floors(unknown) == {} and unknown.at_floor is None
    text = text_report(unknown)
    assert ("  calibration: noise floor unknown: no noise is declared for p1, p2, p3, p4 and "
            "the rows are not time-ordered; declare each reading's noise ('noise: 0.5 um' on "
            "the column or the model input, or in the problem's 'noise:' section) to test "
            "the model against its floor") in text
    header = next(ln for ln in text.splitlines() if ln.lstrip().startswith("dataset"))
    assert "noise floor" not in header          # no column of blanks
    assert json.loads(json_report(unknown))["at_floor"] is None
    assert all(s["floor"] is None and s["chi2_dof"] is None
               for s in json.loads(json_report(unknown))["statistics"])

    ordered = symcal.solve(_bare_problem(tmp_path / "b", time=True), data)
    s = _series(ordered, "g_p")
    assert s.noise.method == "successive differences"
    # the scatter's poses are random in time: successive differences see the noise and the
    # model's remaining error alike, here the noise alone (1 µm), within its sampling error
    assert s.floor == pytest.approx(1e-3, rel=0.15)
    assert "* estimated from the data (successive differences" in text_report(ordered)

    declared = symcal.solve(PLATEN, data)
    assert _series(declared, "g_p").noise.method == "propagated"
    assert _series(declared, "g_p").floor == pytest.approx(2 * 0.503e-3, rel=0.02)


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
    cal, fly = gain.floor_tests
    assert cal.verdict == fly.verdict == "above"
    where = [f"where it fails: calibration: {cal.ratio:.3g}× the noise floor (χ²/dof "
             f"{cal.chi2_dof:.3g}, band {cal.band[0]:.2f}–{cal.band[1]:.2f})",
             f"flyby: {fly.ratio:.3g}× the noise floor (χ²/dof {fly.chi2_dof:.3g}, band "
             f"{fly.band[0]:.2f}–{fly.band[1]:.2f})"]
    regression = (f"calibration made flyby position_y vs reference worse: std "
                  f"{reg.before:.4g} → {reg.after:.4g} µm")
    old = _fake_diagnosis(gain, [_candidate("s2.p_hat += a term linear in theta_raw"),
                                 _candidate("s1.p_hat += harmonic 3 of s1.p")])
    lines = diagnosis_verdict(old)
    assert lines[:3] == ["solved: 1 stage converged (linear)", *where]
    assert lines[3].startswith("worst against its noise floor: ")
    assert lines[4].startswith("against the reference, above the noise floor: ")
    assert lines[5:] == [
        regression,
        "what to add: s2.p_hat += a term linear in theta_raw (and 1 more significant, below)",
        "what cannot be calibrated: 3 parameter direction(s) the data cannot determine"]
    new = _fake_diagnosis(gain, uncalibratable=(_candidate("s1.p_hat += harmonic 1 of s4.p"),))
    assert diagnosis_verdict(new)[-2:] == [
        "what to add: no candidate effect passes the test, yet the residuals are above the "
        "noise floor: structure remains that no candidate explains (or the readings are "
        "noisier than declared)",
        "what cannot be calibrated: s1.p_hat += harmonic 1 of s4.p (real, but these "
        "constraints cannot determine it); 3 parameter direction(s) the data cannot "
        "determine"]


@pytest.mark.slow
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
    stats = _series(gain, "g_p", "flyby")
    floor, (lo, hi) = stats.floor, stats.noise.band
    std = float(np.std(next(v for v in gain_diagnosis.residuals
                             if (v.dataset, v.name) == ("flyby", "g_p")).after)) / 1e-3
    assert (f"  flyby g_p: std {std:.4g} µm (noise floor {floor / 1e-3:.4g} µm; "
            f"{std / (floor / 1e-3):.2f} ×; χ²/dof {stats.chi2_dof:.3g}, band "
            f"{lo:.2f}–{hi:.2f})") in text
    assert not ASCII_MICRO.search(text)


@pytest.mark.slow
def test_diagnosis_document(gain: symcal.Result, gain_diagnosis) -> None:
    doc = diagnosis_document(gain_diagnosis, series=True)
    json.dumps(doc)
    assert [(r["dataset"], r["name"]) for r in doc["regressions"]] == [("flyby", "position_y")]
    assert doc["verdict"] == diagnosis_verdict(gain_diagnosis)
    rows = {(r["dataset"], r["name"]): r for r in doc["residuals"]}
    for key in (("flyby", "g_p"), ("flyby", "position_y")):
        stats = _series(gain, key[1], key[0])
        assert rows[key]["noise_floor"] == pytest.approx(stats.floor / 1e-3)
        assert rows[key]["chi2_dof"] == pytest.approx(stats.chi2_dof)
    assert doc["at_floor"] is False
    assert [(e["dataset"], e["name"], e["floor"], e["chi2_dof"]) for e in doc["statistics"]] \
        == [(t.dataset, t.name, pytest.approx(t.floor / 1e-3 if t.unit == "um" else t.floor
                                               / 1e-3), pytest.approx(t.chi2_dof))
            for t in gain.statistics]
    assert rows[("flyby", "position_y")]["contains"] == ["p_y", "position_y"]
    assert rows[("flyby", "theta_x")]["contains"] == ["theta_x"]
    # what is left above the floor, shown whether or not a candidate explains it
    assert doc["left"] and doc["left"][0].startswith("calibration g_p: ")
    assert all(row["left"] for row in doc["residuals"]
               if _series(gain, row["name"], row["dataset"]).noise.verdict == "above")
    text = diagnosis_report(gain_diagnosis)
    section = text.split("What is left above the noise floor")[1].split("\n\n")[0]
    assert [ln.strip() for ln in section.splitlines()[1:]] == doc["left"]
    assert "<h2>What is left above the noise floor</h2>" in html_report(doc, text)
    # each candidate's minimal detectable effect, in the unit of the residuals (µm)
    assert all(c["mde"] > 0 and c["mde_unit"] == "um" for c in doc["candidates"]
               if c["label"] != "the model's approximation: errors evaluated at the raw "
               "readings")
    assert "detectable from" in text.split("Which effect is missing")[1].splitlines()[1]
    units = {b["variable"]: b["unit"] for r in doc["residuals"] for b in r["binned"]}
    assert units.get("theta_x", "mrad") == "mrad"
    assert all(u == "mm" for v, u in units.items() if v.startswith("phase of s"))
    assert rows[("flyby", "g_p")]["series"]["x"]["unit"] == "mm"


@pytest.mark.slow
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


def test_worse_is_judged_by_test_where_the_floor_is_known(gain: symcal.Result,
                                                          tmp_path: Path) -> None:
    """The gain fixture's fly-by position: std 8.1 → 18.8 µm, above its floor and its
    χ²/dof grown far beyond what noise moves it: worse by test.  The fly-by θx grows 14 %
    (0.073 → 0.083 mrad) but stays at its floor: not worse."""
    position, theta = _series(gain, "position_y", "flyby"), _series(gain, "theta_x", "flyby")
    assert position.noise.worse and position.noise.verdict == "above"
    grown = position.chi2_dof - position.noise.chi2_before / position.noise.dof
    assert grown > position.noise.band[1] - 1
    assert not theta.noise.worse and theta.noise.verdict == "at"
    assert 1.1 < theta.after.std / theta.before.std < 1.2
    loaded = symcal.Result.load(gain.save(tmp_path / "result.json"))
    assert _series(loaded, "position_y", "flyby").noise == position.noise
