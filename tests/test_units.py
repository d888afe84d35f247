"""Units: checked once at load (symcal.language.dimensions over the parse), converted (a model in m
and deg solves to the same physical estimate as its mm/rad twin and is reported in its own
units), unknown units refused with a suggestion, derived units of candidate effects."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

import symcal
from symcal.analysis.discovery import Basis, Candidate
from symcal.base import units
from symcal.base.errors import SpecError
from symcal.report.text import text_report
from symcal.revise import effects

# ------------------------------------------------------------------------ unit sizes


def test_sizes_in_internal_units_are_exact() -> None:
    # independent of pint: the definitions of the units, in mm and rad
    assert units.size("um") == 1e-3 and units.size("nm") == 1e-6 and units.size("m") == 1e3
    assert units.size("inch") == 25.4 and units.size("km") == 1e6
    assert units.size("mrad") == 1e-3 and units.size("urad") == 1e-6
    assert units.size("deg") == math.pi / 180 and units.size("turn") == 2 * math.pi
    assert units.size("min") == 60.0 and units.size("ms") == 1e-3
    assert units.size("m/s") == 1e3 and units.size("mm/deg") == pytest.approx(180 / math.pi)
    assert units.size("") == units.size("1") == units.size("(internal)") == 1.0
    assert [units.internal_unit(u) for u in ("um", "m", "deg", "mrad", "s", "m/s", "", "1")] \
        == ["mm", "mm", "rad", "rad", "s", "mm/s", "", ""]
    assert units.is_angle("deg") and units.is_angle("mrad") and not units.is_angle("mm/m")


def test_unknown_and_offset_units_are_refused() -> None:
    assert units.check_unit("furlong") is None            # exotic but valid: a length
    assert units.check_unit("mmm") == "unknown unit 'mmm' (did you mean 'mm'?)"
    assert units.check_unit("degC") == (
        "unit 'degC' has an offset (0 degC is 273.15 K): symcal converts units by scaling "
        "alone, which cannot carry an offset; use 'kelvin' for a temperature, or "
        "'delta_degC' for a temperature difference")
    assert units.size("kelvin") == units.size("delta_degC") == 1.0     # the alternatives
    assert units.size("delta_degF") == pytest.approx(5 / 9)
    assert units.check_unit("1000 mm") == "'1000 mm' is not a unit (it holds a number)"


@pytest.mark.slow
def test_import_symcal_does_not_import_pint() -> None:
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    code = ("import sys, symcal; print('pint' in sys.modules); "
            "symcal.load_problem('problems/platen_self_calibration.yaml'); "
            "print('pint' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=root)
    assert out.stdout.split() == ["False", "True"]   # imported where units are checked


# ------------------------------------------------------------------ the toy models

ENC = """\
model: enc
doc: a rotary encoder read in {ang}, with its zero offset
inputs:
  q: {{unit: {ang}}}
parameters:
  q0: {{value: 0, unit: {ang}, scale: {q0_scale}}}
expressions:
  e: q0
outputs:
  angle: {{expr: q + e, unit: {ang}}}
"""

LIN = """\
model: lin
doc: a linear scale read in {len}, with its zero offset
inputs:
  x: {{unit: {len}}}
parameters:
  x0: {{value: 0, unit: {len}, scale: {x0_scale}}}
expressions:
  e: x0
outputs:
  pos: {{expr: x + e, unit: {len}}}
"""

PROBLEM = """\
problem: arm
doc: a link of unknown length on an encoder, its tip read by two linear scales
columns:
  t: {{unit: s, role: time}}
  q: {{unit: {ang}}}
  x: {{unit: {len}}}
  y: {{unit: {len}}}
parameters:
  L: {{value: {L0}, unit: {len}, scale: {L0}}}
instances:
  enc: {{model: enc.yaml, inputs: {{q: q}}}}
  sx: {{model: lin.yaml, inputs: {{x: x}}}}
  sy: {{model: lin.yaml, inputs: {{x: y}}}}
constraints:
  g_x: L*cos(enc.angle) - sx.pos
  g_y: L*sin(enc.angle) - sy.pos
datasets:
  calibration: {{path: data.csv}}
"""

TRUTH = {"L": 350.0, "q0": math.radians(2.5), "x0": 12.0, "y0": -4.0}   # mm, rad
SIGMA = 0.01   # mm


def _data(n: int = 200, seed: int = 3) -> dict[str, np.ndarray]:
    """Readings in mm and rad: the tip of the link seen by the scales, with noise."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1.0, 1.0, n)
    angle = q + TRUTH["q0"]
    x = TRUTH["L"] * np.cos(angle) - TRUTH["x0"] + rng.normal(0, SIGMA, n)
    y = TRUTH["L"] * np.sin(angle) - TRUTH["y0"] + rng.normal(0, SIGMA, n)
    return {"t": np.arange(n) * 0.1, "q": q, "x": x, "y": y}


def _write(folder: Path, length: str, angle: str) -> Path:
    """The toy problem in ``length`` and ``angle`` units, with its data in them."""
    folder.mkdir(parents=True, exist_ok=True)
    f_len, f_ang = units.size(length), units.size(angle)   # internal units per unit
    fmt = {"len": length, "ang": angle, "L0": f"{300.0 / f_len:g}",
           "q0_scale": f"{0.01 / f_ang:g}", "x0_scale": f"{10.0 / f_len:g}"}
    (folder / "enc.yaml").write_text(ENC.format(**fmt))
    (folder / "lin.yaml").write_text(LIN.format(**fmt))
    (folder / "problem.yaml").write_text(PROBLEM.format(**fmt))
    d = _data()
    cols = {"t": d["t"], "q": d["q"] / f_ang, "x": d["x"] / f_len, "y": d["y"] / f_len}
    lines = ["t,q,x,y"] + [",".join(repr(float(cols[c][i])) for c in cols)
                           for i in range(len(d["t"]))]
    (folder / "data.csv").write_text("\n".join(lines) + "\n")
    return folder / "problem.yaml"


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> dict[str, symcal.Result]:
    root = tmp_path_factory.mktemp("units")
    out = {}
    for key, (length, angle) in {"mm": ("mm", "rad"), "m": ("m", "deg")}.items():
        path = _write(root / key, length, angle)
        out[key] = symcal.solve(symcal.load_problem(path))
    return out


# ------------------------------------------------------------------- conversion


def test_a_model_in_m_and_deg_solves_to_the_same_physical_estimate(solved) -> None:
    mm, m = solved["mm"], solved["m"]
    assert mm.success and m.success
    to_internal = {"L": 1e3, "enc.q0": math.pi / 180, "sx.x0": 1e3, "sy.x0": 1e3}
    for name, factor in to_internal.items():
        assert m.params[name].value * factor == pytest.approx(mm.params[name].value, rel=1e-9,
                                                              abs=1e-12)
    # and both recover the truth within 3 standard errors (in internal units)
    se = {p.name: p.se for p in mm.params.values()}
    truth = {"L": TRUTH["L"], "enc.q0": TRUTH["q0"], "sx.x0": TRUTH["x0"],
             "sy.x0": TRUTH["y0"]}
    for name, value in truth.items():
        assert abs(mm.params[name].value - value) < 3 * se[name], name
    # standard errors convert too
    se_m = {p.name: p.se for p in m.params.values()}
    for name, factor in to_internal.items():
        assert se_m[name] * factor == pytest.approx(se[name], rel=1e-6)


def test_the_model_in_m_and_deg_is_reported_in_m_and_deg(solved) -> None:
    mm, m = solved["mm"], solved["m"]
    assert {c.name: c.unit for c in m.problem.constraints} == {"g_x": "m", "g_y": "m"}
    assert {c.name: c.unit for c in mm.problem.constraints} == {"g_x": "mm", "g_y": "mm"}
    std_m = m.stat("g_x", "calibration").shown("after").std
    std_mm = mm.stat("g_x", "calibration").shown("after").std
    assert std_m * 1e3 == pytest.approx(std_mm, rel=1e-6)
    assert 0.5 * SIGMA < std_mm < 2 * SIGMA       # the noise, in mm
    text = text_report(m)
    # the residual row is in metres, with the value in metres
    row = next(line for line in text.splitlines()
               if line.strip().startswith("calibration") and " g_x " in f" {line} ")
    assert re.search(r"\bm\b", row) and " mm" not in row
    assert f"{std_m:.4g}" in row
    # parameters in their own units
    param = next(line for line in text.splitlines() if line.strip().startswith("enc.q0"))
    assert param.split()[1] == f"{m.params['enc.q0'].value:.6g}" and param.split()[-1] == "deg"


# --------------------------------------------------------------- dimension errors

SEG = """\
model: seg
constants:
  rho: {value: 1.016, unit: mm}
inputs:
  p: {unit: mm, period: rho}
parameters:
  k0: {value: 0, unit: mm}
  k1: {value: 0, unit: mm}
  tilt: {value: 0, unit: rad}
expressions:
  e: EXPR
outputs:
  p_hat: {expr: p + e, unit: OUT}
"""

TOY = """\
problem: toy
columns:
  p1: {unit: mm}
  p2: {unit: mm}
  th: {unit: COL}
instances:
  s1: {model: seg.yaml, inputs: {p: p1}}
  s2: {model: seg.yaml, inputs: {p: p2}}
constraints:
  g: {expr: s1.p_hat - s2.p_hat, unit: um}
comparisons:
  c: {estimate: s1.p_hat, reference: REF}
datasets:
  calibration: {path: data.csv}
"""


def _load(tmp_path: Path, expr_text: str = "k0 + k1*sin(2*pi*p/rho)", out: str = "mm",
          col: str = "rad", ref: str = "p1") -> symcal.Problem:
    (tmp_path / "seg.yaml").write_text(SEG.replace("EXPR", expr_text).replace("OUT", out))
    (tmp_path / "toy.yaml").write_text(TOY.replace("COL", col).replace("REF", ref))
    return symcal.load_problem(tmp_path / "toy.yaml")


def _error(tmp_path: Path, **kw: str) -> str:
    with pytest.raises(SpecError) as err:
        _load(tmp_path, **kw)
    return str(err.value).replace(f"{tmp_path}/", "")


def test_the_well_formed_toy_loads(tmp_path: Path) -> None:
    problem = _load(tmp_path)
    assert problem.constraint("g").unit == "um"


def test_adding_mm_to_rad_names_both_sides_the_file_and_line(tmp_path: Path) -> None:
    assert _error(tmp_path, expr_text="k0 + tilt") == (
        "seg.yaml:11: expressions.e: cannot add 'k0' (mm, a length) and 'tilt' (rad, an "
        "angle)")
    assert _error(tmp_path, expr_text="tilt - k1*tilt") == (
        "seg.yaml:11: expressions.e: cannot subtract 'k1*tilt' (mm*rad, a length) from "
        "'tilt' (rad, an angle)")


def test_functions_need_their_units(tmp_path: Path) -> None:
    assert _error(tmp_path, expr_text="k0 + k1*sin(p)") == (
        "seg.yaml:11: expressions.e: sin() needs an angle or a dimensionless ratio, but 'p' "
        "is in mm, a length (at column 9)")
    assert _error(tmp_path, expr_text="k0 + k1*exp(tilt*p)") == (
        "seg.yaml:11: expressions.e: exp() needs a dimensionless argument, but 'tilt*p' is "
        "in mm*rad, a length (at column 9)")
    assert _error(tmp_path, expr_text="k0 + p**k1") == (
        "seg.yaml:11: expressions.e: the exponent 'k1' of 'p' must be dimensionless, found "
        "mm, a length")
    assert _error(tmp_path, expr_text="k0 + p**tilt") == (
        "seg.yaml:11: expressions.e: 'p' has a unit (mm, a length): its exponent 'tilt' must "
        "be a number")
    # powers and roots with numbers are fine, and atan2 of two lengths is an angle
    problem = _load(tmp_path, expr_text="sqrt(k0**2 + k1**2) + k0*atan2(p, rho)")
    assert problem.constraint("g").unit == "um"


def test_declared_units_are_checked_against_the_expression(tmp_path: Path) -> None:
    assert _error(tmp_path, out="mrad") == (
        "seg.yaml:13: outputs.p_hat.expr: 'p_hat' is declared in mrad, an angle, but its "
        "expression is in mm, a length")
    assert _error(tmp_path, ref="th") == (
        "toy.yaml:12: comparisons.c: comparison 'c': the estimate 's1.p_hat' is in mm, a "
        "length, but the reference 'th' is in rad, an angle")


def test_a_models_expression_may_declare_its_unit(tmp_path: Path) -> None:
    """A model's expression written as ``{expr, unit, doc}``, as a problem's expressions
    and a model's outputs are (a new user's model was refused): it builds the same
    constraint as the text form, and its unit is checked against the expression."""
    text = _load(tmp_path).constraint("g").sx
    form = "{expr: k0 + k1*sin(2*pi*p/rho), unit: um, doc: the segment's error}"
    problem = _load(tmp_path, expr_text=form)
    assert str(problem.constraint("g").sx) == str(text)
    assert _error(tmp_path, expr_text="{expr: k0 + k1*sin(2*pi*p/rho), unit: rad}") == (
        "seg.yaml:11: expressions.e.expr: 'e' is declared in rad, an angle, but its "
        "expression is in mm, a length")
    assert _error(tmp_path, expr_text="{expr: k0, units: mm}") == (
        "seg.yaml:11: expressions.e.units: unknown key 'units' (did you mean 'unit'?); allowed "
        "keys: expr, unit, doc")


def test_inputs_are_checked_against_their_bindings(tmp_path: Path) -> None:
    (tmp_path / "seg.yaml").write_text(SEG.replace("EXPR", "k0").replace("OUT", "mm"))
    (tmp_path / "toy.yaml").write_text(TOY.replace("COL", "deg").replace("REF", "p1")
                                       .replace("inputs: {p: p2}", "inputs: {p: th}"))
    with pytest.raises(SpecError) as err:
        symcal.load_problem(tmp_path / "toy.yaml")
    assert str(err.value).replace(f"{tmp_path}/", "") == (
        "toy.yaml:8: instances.s2.inputs.p: input 'p' of model 'seg' is in mm, a length, but "
        "'th' bound to it is in deg, an angle")


def test_unknown_unit_is_refused_with_a_suggestion(tmp_path: Path) -> None:
    assert _error(tmp_path, col="mmm") == (
        "toy.yaml:5: columns.th.unit: unknown unit 'mmm' (did you mean 'mm'?); units are "
        "pint's (mm, um, m, rad, mrad, deg, s, mm/s, ...)")
    assert _error(tmp_path, out="milimeter") == (
        "seg.yaml:13: outputs.p_hat.unit: unknown unit 'milimeter' (did you mean "
        "'millimeter'?); units are pint's (mm, um, m, rad, mrad, deg, s, mm/s, ...)")
    # an exotic unit of the right dimension is accepted and converted
    problem = _load(tmp_path, out="furlong")
    assert problem.signals[0].unit == "furlong"


# ------------------------------------------------------------- candidate effects


def test_derived_units_of_candidate_effects_load_and_check(solved, tmp_path: Path) -> None:
    problem = solved["m"].problem
    centre = 0.0123   # rad, internal units
    linear = Candidate("sx.pos", Basis("linear", "q", "a term linear in q", ("lin",),
                                       ("({v} - {centre})",), unit="deg", scales=(0.01,),
                                       centre=centre))
    drift = Candidate("sy.pos", Basis("drift", "t", "a slow drift in time (t)", ("drift",),
                                      ("{v}",), unit="s", scales=(0.001,)))
    harmonic = Candidate("enc.angle", Basis("harmonic", "enc.q", "harmonic 1 of enc.q",
                                            ("h1_sin", "h1_cos"),
                                            ("sin(2*pi*{v}/{period})",
                                             "cos(2*pi*{v}/{period})"), unit="deg",
                                            scales=(0.001, 0.001), period=2 * math.pi))
    text = effects.suggestion(problem, linear).model_text("lin.yaml")
    # the coefficient: the output's declared unit (m) per the variable's, an angle in rad;
    # its scale (0.01 mm/rad internal) in that unit; the centre in rad
    assert "lin_q: {value: 0, unit: m/rad, scale: 1e-05}" in text
    assert f"c_lin_q: {{value: {centre:g}, unit: rad, doc: reference" in text
    assert "e: base.e + lin_q*(v_q - c_lin_q)" in text
    assert "v_q: {doc: bound to q in the problem, unit: rad}" in text
    assert "drift_t: {value: 0, unit: m/s, scale: 1e-06}" in \
        effects.suggestion(problem, drift).model_text("lin.yaml")
    assert "P_h1_q: {value: 6.28318530718, unit: rad}" in \
        effects.suggestion(problem, harmonic).model_text("enc.yaml")
    for k, cand in enumerate((linear, drift, harmonic)):
        revised = effects.revised_problem(problem, cand, tmp_path / str(k))
        added = [p for p in revised.parameters if p.name not in problem.index]
        assert [p.unit for p in added] == {0: ["m/rad"], 1: ["m/s"], 2: ["deg", "deg"]}[k]
