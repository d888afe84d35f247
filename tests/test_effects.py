"""Candidate effects as files that load (issue 23 items 4 and 7): every kind written on the
bundled courier problems and the two new examples loads back; units a person reads and
scales within symcal's range from declared units (SI, degrees, volts, counts); one file
per candidate, never written over another's; and the files do what they say (a constant
made a parameter, a freed parameter, a latency and a product recovered from simulated
truth)."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import courier_scenarios
import numpy as np
import pytest

import symcal
from symcal.analysis.discovery import Basis, Candidate
from symcal.base.units import is_angle, size
from symcal.data.dataset import make_dataset
from symcal.revise import effects
from symcal.revise.effects import per, scale_in
from symcal.simulation import simulate_run

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = [ROOT / "problems" / f for f in (
    "platen_self_calibration.yaml", "platen_self_calibration_implicit.yaml",
    "dual_sensor_calibration.yaml", "dual_sensor_calibration_implicit.yaml")] + [
    ROOT / "examples" / d / f for d in ("accelerometer_triad", "diff_drive")
    for f in ("problem.yaml", "problem_fixed.yaml")]


def _signal(problem: symcal.Problem, name: str):
    return next(q for q in problem.signals if q.name == name)


def every_kind(problem: symcal.Problem) -> list[Candidate]:
    """One candidate of each kind that applies to ``problem``, built from its structure as
    a search would: on the first instance's first output, in its own first input."""
    inst = next(iter(problem.instances.values()))
    output = f"{inst.name}.{next(iter(inst.model.outputs))}"
    v = f"{inst.name}.{next(iter(inst.model.inputs))}"
    unit = _signal(problem, v).unit
    time = next((c for c, s in problem.column_specs.items() if s.role == "time"), None)
    periodic = next((q for q in problem.signals if q.period and q.name.startswith(
        inst.name + ".")), None)
    angle = next((q for q in problem.expressions if is_angle(q.unit)), None)
    out: list[Candidate] = []
    period = periodic.period if periodic else 10.0 * size(unit)
    hv = periodic.name if periodic else v
    out.append(Candidate(output, Basis(
        "harmonic", hv, f"harmonic 2 of {hv}", ("h2_sin", "h2_cos"),
        ("sin(4*pi*{v}/{period})", "cos(4*pi*{v}/{period})"), order=2,
        unit=_signal(problem, hv).unit, scales=(1e-3, 1e-3), period=period)))
    out.append(Candidate(output, Basis(
        "linear", v, f"a term linear in {v}", ("lin",), ("({v} - {centre})",), unit=unit,
        scales=(1e-4,), centre=0.5 * size(unit))))
    out.append(Candidate(output, Basis(
        "quadratic", v, f"a quadratic dependence on {v}", ("lin", "quad"),
        ("({v} - {centre})", "({v} - {centre})**2"), unit=unit, scales=(1e-4, 1e-6),
        centre=0.5 * size(unit))))
    if time is not None:
        tu = problem.column_specs[time].unit
        out.append(Candidate(output, Basis(
            "drift", time, f"a slow drift in time ({time})", ("drift",), ("{v}",), unit=tu,
            scales=(1e-5,))))
        out.append(Candidate(output, Basis(
            "product", v, f"{v} times {time}", ("prod",),
            ("({v} - {centre})*({w} - {other_centre})",), unit=unit, scales=(1e-6,),
            centre=0.1 * size(unit), other=time, other_unit=tu, other_centre=2.0)))
    if angle is not None and periodic is not None:
        out.append(Candidate(output, Basis(
            "angle_harmonic", periodic.name, f"{angle.name} times harmonic 1 of "
            f"{periodic.name}", ("ah_sin", "ah_cos"),
            ("{a}*sin(2*pi*{v}/{period})", "{a}*cos(2*pi*{v}/{period})"), angle.name,
            unit=periodic.unit, angle_unit=angle.unit, scales=(1e-2, 1e-2),
            period=periodic.period)))
    groups: dict[tuple[str, float], list[str]] = {}
    for c in problem.constants:
        groups.setdefault((c.name, c.value * size(c.unit)), []).append(c.key)
    if groups:
        keys = max(groups.values(), key=len)
        out.append(Candidate("(constant)", Basis(
            "constant", keys[0], f"the constant {keys[0]} is off", (), (),
            targets=tuple(keys), scales=(1e-4,))))
    fixed = next((p.name for p in problem.parameters if p.fixed), None)
    if fixed is not None:
        out.append(Candidate("(fixed)", Basis(
            "fixed", fixed, f"the fixed {fixed} is off", (), (), targets=(fixed,))))
    bare = {name: text for name, text in inst.bindings.items()
            if text in problem.column_specs}
    if time is not None and bare:
        out.append(Candidate("(latency)", Basis(
            "latency", inst.name, f"{inst.name} reads late", (), (),
            targets=tuple(bare.values()), scales=(1e-3,))))
    return out


@pytest.mark.parametrize("path", [
    p if p in (PROBLEMS[0],)   # the others: slow
    else pytest.param(p, marks=pytest.mark.slow) for p in PROBLEMS],
    ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_kind_is_written_as_files_that_load(path: Path, tmp_path: Path) -> None:
    """Each kind that applies: the files load, add what the kind says, and no two
    candidates share a file."""
    problem = symcal.load_problem(path)
    written: list[Path] = []
    kinds = set()
    for cand in every_kind(problem):
        before = set(tmp_path.rglob("*.yaml"))
        overlay = effects.write_revision(problem, cand, tmp_path)
        new = set(tmp_path.rglob("*.yaml")) - before
        assert overlay in new, cand.label            # its own overlay, nothing rewritten
        written += sorted(new)
        revised = symcal.load_problem(overlay)
        added = [p for p in revised.parameters if p.name not in problem.index]
        kind = cand.basis.kind
        kinds.add(kind)
        if kind in effects.TERMS:
            assert len(added) == len(cand.basis.columns), cand.label
            assert any(q.name == cand.output for q in revised.signals)
            assert _signal(revised, cand.output).unit == _signal(problem, cand.output).unit
            text = next(p for p in new if p.parent.name == "models").read_text()
            assert "^0.5" not in text and "µ" not in text
            for p in added:
                assert p.scale is None or 1e-9 <= p.scale <= 1e9
        elif kind == "constant":
            assert len(added) == 1 and added[0].doc.endswith("(was a constant)")
            assert added[0].value == next(c.value for c in problem.constants
                                          if c.key == cand.basis.targets[0])
            assert not {c.key for c in revised.constants} & set(cand.basis.targets)
        elif kind == "fixed":
            freed = revised.parameters[revised.index[cand.basis.targets[0]]]
            assert not added and not freed.fixed
            assert freed.value == problem.parameters[problem.index[freed.name]].value
        elif kind == "latency":
            assert [p.unit for p in added] == ["s"]
            rates = {k for k, c in revised.column_specs.items() if c.rate_of}
            assert {revised.column_specs[r].rate_of for r in rates} == set(
                cand.basis.targets)
    assert len(written) == len(set(written))
    assert {"harmonic", "linear", "quadratic"} <= kinds


def _solve(overlay: Path) -> symcal.Result:
    return symcal.solve(symcal.load_problem(overlay))


@pytest.mark.parametrize("path", [PROBLEMS[0], PROBLEMS[5], PROBLEMS[7],
                                  pytest.param(PROBLEMS[2], marks=pytest.mark.slow)],
                         ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_a_revision_of_each_system_solves(path: Path, tmp_path: Path) -> None:
    problem = symcal.load_problem(path)
    cand = next(c for c in every_kind(problem) if c.basis.kind == "drift")
    result = _solve(effects.write_revision(problem, cand, tmp_path))
    assert result.success
    assert set(result.params) > set(problem.parameter_names)


# --------------------------------------------------------------------------- units


@pytest.mark.parametrize(("numerator", "denominators", "unit"), [
    ("m/s**2", [("K", 1)], "m/K/s^2"),             # a triad's temperature coefficient
    ("m/s**2", [("m/s**2", 1)], ""),               # a ratio: no unit
    ("m/s**2", [("m/s**2", 2)], "s^2/m"),
    ("G", [("K", 1)], "G/K"),                      # a magnetometer in gauss
    ("V", [("count", 1)], "V/count"),
    ("m/s", [("rad/s", 1)], "m/rad"),              # what cancels is cancelled
    ("um", [("mm", 1)], ""),
    ("um", [("mm/s", 1)], "s"),                    # two lengths left: internal units
    ("mm", [("s", 1), ("mm", 1)], "1/s"),
    ("deg", [], "deg"),
])
def test_coefficient_units_are_ones_a_person_reads(numerator, denominators, unit) -> None:
    assert per(numerator, *denominators) == unit


def test_scales_are_written_in_the_coefficients_unit_within_range() -> None:
    assert scale_in(3.3e-11, "s^2/m") == 3.3e-08       # the triad's quadratic: no crash
    assert scale_in(0.0014, "mm") == 0.0014
    assert scale_in(0.0014, "um") == 1.4
    assert scale_in(1e-15, "") == 1e-9                 # beyond symcal's range: its edge
    assert scale_in(0.0, "mm") == 1.0 and scale_in(math.nan, "mm") == 1.0


def test_the_triad_in_si_units_gets_loadable_candidates(tmp_path: Path) -> None:
    """The scales a search sizes from the data in internal units (a quadratic in a reading
    of ~10 m/s², 3.3e-11 (mm/s²)⁻¹: what crashed) are written in the coefficient's unit
    and load; the coefficients' units are the output's over the reading's."""
    problem = symcal.load_problem(ROOT / "examples" / "accelerometer_triad" / "problem.yaml")
    cand = Candidate("acc.fx", Basis(
        "quadratic", "acc.ax", "a quadratic dependence on acc.ax", ("lin", "quad"),
        ("({v} - {centre})", "({v} - {centre})**2"), unit="m/s**2",
        scales=(1.7e-7, 3.3e-11), centre=120.0))
    text = effects.suggestion(problem, cand).model_text("triad.yaml")
    assert "lin_ax: {value: 0, scale: 1.7e-07}" in text                # a ratio
    assert "quad_ax: {value: 0, unit: s^2/m, scale: 3.3e-08}" in text
    # the centre as declared
    assert "c_quad_ax: {value: 0.12, unit: m/s**2, doc: reference" in text
    assert "fx: base.fx + lin_ax*(ax - c_quad_ax) + quad_ax*(ax - c_quad_ax)**2" in text
    revised = effects.revised_problem(problem, cand, tmp_path)
    assert _signal(revised, "acc.fx").unit == "m/s**2"                 # kept as declared


def test_a_state_column_in_kelvin(tmp_path: Path) -> None:
    """A temperature declared as a state of the environment: the coefficient of a term in
    it reads m/K/s^2, and the centre is in K."""
    home = tmp_path / "triad"
    shutil.copytree(ROOT / "examples" / "accelerometer_triad", home)
    (home / "warm.yaml").write_text(
        "problem: warm\nextends: problem.yaml\n"
        "columns: {T: {unit: K, role: state, doc: ambient temperature}}\n")
    problem = symcal.load_problem(home / "warm.yaml")
    assert problem.column_role("T") == "state"
    cand = Candidate("acc.fz", Basis("linear", "T", "a term linear in T", ("lin",),
                                     ("({v} - {centre})",), unit="K", scales=(2e-3,),
                                     centre=296.5))
    text = effects.suggestion(problem, cand).model_text("triad.yaml")
    assert "lin_T: {value: 0, unit: m/K/s^2, scale: 2e-06}" in text
    assert "c_lin_T: {value: 296.5, unit: K, doc: reference" in text
    assert "v_T: {doc: bound to T in the problem, unit: K}" in text
    assert symcal.load_problem(effects.write_revision(problem, cand, home / "out"))


def test_a_term_on_an_output_without_an_error_expression_keeps_its_unit(tmp_path) -> None:
    """The coordination sensor's c_y (no `reading + error` form) gets its term on the
    output in the short form, and keeps mm; a term in c_x, its other output, uses it by
    name (no new input bound to another instance)."""
    problem = symcal.load_problem(ROOT / "problems" / "dual_sensor_calibration.yaml")
    cand = Candidate("cs.c_y", Basis("linear", "cs.c_x", "a term linear in cs.c_x",
                                     ("lin",), ("({v} - {centre})",), unit="mm",
                                     scales=(1e-3,), centre=1.25))
    sug = effects.suggestion(problem, cand)
    assert sug.body["outputs"] == {"c_y": "base.c_y + lin_c_x*(c_x - c_lin_c_x)"}
    assert not sug.new_inputs and sug.body["parameters"] == {
        "lin_c_x": {"value": 0, "scale": 0.001}}
    revised = effects.revised_problem(problem, cand, tmp_path)
    assert _signal(revised, "cs.c_y").unit == "mm"
    itself = Candidate("cs.c_y", Basis("linear", "cs.c_y", "a term linear in cs.c_y",
                                       ("lin",), ("({v} - {centre})",), unit="mm"))
    with pytest.raises(ValueError, match="cannot depend on cs.c_y itself"):
        effects.suggestion(problem, itself)


# --------------------------------------------------------------------------- file names


def _harmonic(instance: str) -> Candidate:
    return Candidate(f"{instance}.p_hat", Basis(
        "harmonic", f"{instance}.p", f"harmonic 3 of {instance}.p (period 1.016 mm)",
        ("h3_sin", "h3_cos"), ("sin(6*pi*{v}/{period})", "cos(6*pi*{v}/{period})"), order=3,
        unit="mm", scales=(0.0014, 0.0014), period=1.016))


def test_one_file_per_candidate_never_written_over_another(tmp_path: Path) -> None:
    problem = symcal.load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    first = effects.write_revision(problem, _harmonic("s1"), tmp_path)
    model = tmp_path / "models" / "platen_segment_p_hat_h3_p.yaml"
    assert first.name == "platen_self_calibration_s1_p_hat_h3_p.yaml"
    kept = model.read_text()
    # the same term in s2 is another candidate: the model of that name is s1's, so s2's
    # gets another name; s1's is left as it was
    second = effects.write_revision(problem, _harmonic("s2"), tmp_path)
    other = tmp_path / "models" / "platen_segment_p_hat_h3_p_2.yaml"
    assert model.read_text() == kept and other.exists()
    assert other.read_text().startswith("model: platen_segment_p_hat_h3_p_2\n")
    assert "models/platen_segment_p_hat_h3_p_2.yaml" in second.read_text()
    # writing a candidate again changes nothing and adds nothing
    files = sorted(tmp_path.rglob("*"))
    assert effects.write_revision(problem, _harmonic("s1"), tmp_path) == first
    assert sorted(tmp_path.rglob("*")) == files
    # one overlay name asked for two candidates: the second gets its own, named in it
    a = effects.write_revision(problem, _harmonic("s3"), tmp_path, "round1")
    b = effects.write_revision(problem, _harmonic("s4"), tmp_path, "round1")
    assert (a.name, b.name) == ("round1.yaml", "round1_2.yaml")
    assert b.read_text().startswith("problem: round1_2\n")
    assert "s3" in a.read_text() and "s4" in b.read_text()
    for path in (first, second, a, b):
        assert symcal.load_problem(path)


def test_printed_overlays_of_other_kinds_load_as_printed(tmp_path: Path) -> None:
    """What diagnose prints for a constant, a freed parameter and a latency: the overlay
    alone, which loads when written beside the problem as the comment says."""
    home = tmp_path / "dd"
    shutil.copytree(ROOT / "examples" / "diff_drive", home)
    problem = symcal.load_problem(home / "problem_fixed.yaml")
    cands = [c for c in every_kind(problem) if c.basis.kind in ("fixed", "latency")]
    assert len(cands) == 2
    for cand in cands:
        text = effects.effect_yaml(problem, cand)
        assert "models/" not in text
        match = re.match(r"# (\S+\.yaml) \(beside problem_fixed.yaml\): the problem with it\n",
                         text)
        assert match is not None
        (home / match.group(1)).write_text(text.split("\n", 1)[1])
        assert symcal.load_problem(home / match.group(1))


# --------------------------------------------------------------------------- the kinds work


def test_a_pitch_that_is_off_is_recovered_as_one_parameter(tmp_path: Path) -> None:
    """The platen's tooth pitch 1 % off (issue 23): the constant kind on s1..s4.rho makes
    one parameter rho, which the self-calibration recovers within 3 standard errors, and
    g_p falls from several times its floor to the floor."""
    truth = 1.016 * 1.01
    scenario = courier_scenarios.platen().overlay({"constants": {"rho": truth}})
    data = {n: make_dataset(n, "simulated", simulate_run(scenario, n, seed=5), [])
            for n in ("calibration", "flyby")}
    problem = symcal.load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    before = symcal.solve(problem, data)
    cand = Candidate("(constant)", Basis(
        "constant", "rho", "the constant rho (platen tooth pitch) is off", (), (),
        targets=("s1.rho", "s2.rho", "s3.rho", "s4.rho")))
    text = effects.effect_yaml(problem, cand)
    assert "rho: {value: 1.016, unit: mm, doc: platen tooth pitch (was a constant)}" in text
    after = symcal.solve(effects.revised_problem(problem, cand, tmp_path), data)
    assert after.success
    rho = after.params["rho"]
    assert abs(rho.value - truth) < 3 * rho.se, (rho.value, rho.se)
    g_before = before.stat("g_p").after.std
    g_after = after.stat("g_p").after.std
    assert g_before > 3 * g_after and g_after < 1.1          # um: the floor is ~1.0 um


ENCODERS = """\
model: encoder
doc: an angle encoder with a zero offset
inputs:
  q: {unit: rad, noise: 10 urad}
parameters:
  q0: {value: 0, unit: rad, scale: 0.001}
expressions:
  e: q0
outputs:
  angle: {expr: q + e, unit: rad}
"""

TWO = """\
problem: two
columns:
  t: {unit: s, role: time}
  a: {unit: rad}
  b: {unit: rad}
  T: {unit: K, role: state}
instances:
  e1: {model: encoder.yaml, inputs: {q: a}, parameters: {q0: {fixed: true}}}
  e2: {model: encoder.yaml, inputs: {q: b}}
constraints:
  g: {expr: e1.angle - e2.angle, unit: urad}
datasets:
  calibration: {path: d.csv}
"""


def _two(tmp: Path, columns: dict[str, np.ndarray]) -> symcal.Problem:
    (tmp / "encoder.yaml").write_text(ENCODERS)
    (tmp / "p.yaml").write_text(TWO)
    lines = [",".join(columns)] + [",".join(repr(float(columns[c][i])) for c in columns)
                                   for i in range(len(columns["t"]))]
    (tmp / "d.csv").write_text("\n".join(lines) + "\n")
    return symcal.load_problem(tmp / "p.yaml")


def test_a_latency_is_recovered(tmp_path: Path) -> None:
    """Two encoders on one shaft; the second reads 12 ms late.  The latency kind on e2
    (b + tau*b_rate) recovers the delay within 3 standard errors."""
    rng = np.random.default_rng(11)
    t = np.arange(0, 20, 0.01)
    x = lambda s: 0.8 * np.sin(2 * np.pi * 0.3 * s) + 0.3 * np.sin(2 * np.pi * 1.1 * s)  # noqa: E731
    tau = 0.012
    cols = {"t": t, "a": x(t) + 1e-5 * rng.normal(size=t.size),
            "b": x(t - tau) + 0.002 + 1e-5 * rng.normal(size=t.size), "T": 290 + 0 * t}
    problem = _two(tmp_path, cols)
    cand = Candidate("(latency)", Basis("latency", "e2", "e2 reads late", (), (),
                                        targets=("b",), scales=(1e-3,)))
    overlay = effects.write_revision(problem, cand, tmp_path / "out")
    text = overlay.read_text()
    assert "inputs: {q: b + tau_e2*b_rate}" in text
    assert "b_rate: {rate_of: b, unit: rad/s, noise: 0," in text
    result = symcal.solve(overlay)
    est = result.params["tau_e2"]
    assert est.unit == "s" and abs(est.value - tau) < 3 * est.se, (est.value, est.se)
    assert est.se < 1e-3


def test_a_product_is_recovered(tmp_path: Path) -> None:
    """The second encoder's error grows with its reading times the temperature (a gain
    that drifts with T); the product kind writes c*(b - b0)*(T - T0) and recovers c."""
    rng = np.random.default_rng(12)
    n = 400
    a = rng.uniform(-1, 1, n)
    temp = rng.uniform(285, 305, n)
    c = 2e-4                                            # rad per rad per K
    cols = {"t": np.arange(n) * 0.1, "a": a + 1e-5 * rng.normal(size=n),
            "b": a - c * a * (temp - 295) + 1e-5 * rng.normal(size=n), "T": temp}
    problem = _two(tmp_path, cols)
    cand = Candidate("e2.angle", Basis(
        "product", "e2.q", "e2.q times T", ("prod",),
        ("({v} - {centre})*({w} - {other_centre})",), unit="rad", scales=(1e-5,),
        centre=0.0, other="T", other_unit="K", other_centre=295.0))
    text = effects.suggestion(problem, cand).model_text("encoder.yaml")
    assert "prod_q_T: {value: 0, unit: 1/K, scale: 1e-05}" in text
    assert "e: base.e + prod_q_T*(q - c_prod_q_T)*(v_T - d_prod_q_T)" in text
    result = symcal.solve(effects.revised_problem(problem, cand, tmp_path / "out"))
    est = result.params["e2.prod_q_T"]
    assert abs(est.value - c) < 3 * est.se, (est.value, est.se)


def test_a_freed_parameter_keeps_its_value_and_declaration(tmp_path: Path) -> None:
    problem = symcal.load_problem(ROOT / "examples" / "diff_drive" / "problem_fixed.yaml")
    wheelbase = Candidate("(fixed)", Basis("fixed", "b", "the fixed b is off", (), (),
                                           targets=("b",)))
    gain = Candidate("(fixed)", Basis("fixed", "imu.gain", "the fixed imu.gain is off", (),
                                      (), targets=("imu.gain",)))
    text = effects.effect_yaml(problem, wheelbase)
    assert ("b: {value: 0.312, unit: m, scale: 0.312, fixed: false, doc: wheelbase "
            "(measured)}") in text
    assert "gain: {value: 1.03, scale: 1.0, fixed: false}" in effects.effect_yaml(problem,
                                                                                  gain)
    both = symcal.load_problem(effects.write_revision(problem, wheelbase, tmp_path,
                                                      also=(gain,)))
    for name, value in (("b", 0.312), ("imu.gain", 1.03)):
        p = both.parameters[both.index[name]]
        assert not p.fixed and p.value == value


def test_kinds_that_do_not_apply_are_refused() -> None:
    problem = symcal.load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    with pytest.raises(ValueError, match="different values"):
        effects.revision(problem, Candidate("(constant)", Basis(
            "constant", "rho", "", (), (), targets=("s1.rho", "l_s"))))
    with pytest.raises(ValueError, match="no constant s9.rho"):
        effects.revision(problem, Candidate("(constant)", Basis(
            "constant", "rho", "", (), (), targets=("s9.rho",))))
    with pytest.raises(ValueError, match="reads none of t"):
        effects.revision(problem, Candidate("(latency)", Basis(
            "latency", "s1", "", (), (), targets=("t",))))
    with pytest.raises(ValueError, match="not a term on one output"):
        effects.suggestion(problem, Candidate("(constant)", Basis(
            "constant", "rho", "", (), (), targets=("s1.rho",))))

