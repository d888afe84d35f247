"""C export: the generated code compiles warning-free and agrees with symcal's Python.

The generated functions are compiled with the system C compiler and evaluated on the
first N_OBS observations of each problem's calibration dataset; every residual, every
entry of the Jacobian and every instance output must agree with symcal's own evaluation
of the problem's SX (``symcal.base.numeric.mapped``), converted from symcal's internal
units (mm, rad, s) to the unit the YAML declares by the hand-written table SIZE, to RTOL
relative.  Values below 1 internal unit are held to RTOL absolute (in internal units)
instead: the residuals are differences of readings of order 1-100 mm, so their rounding
is relative to those.  An accelerometer read in m/s**2, with a tilt output in degrees,
checks the units end to end, also against numpy.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.base.numeric import mapped
from symcal.calibrate.solve import load_datasets
from symcal.cli import codegen as cli_codegen
from symcal.export import c as codegen
from symcal.export import render
from symcal.problem.symbolic import Problem, Quantity

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"
CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler ('cc' or 'gcc') on PATH")
N_OBS = 200
RTOL = 1e-12
#: The test driver is built with every warning an error; -O0 keeps compiling fast.
STRICT = ["-std=c99", "-O0", "-Wall", "-Wextra", "-Werror", "-pedantic"]
#: The size of each unit the tests meet in symcal's internal units (mm, rad, s), written
#: out by hand: the C's value is symcal's internal value divided by it.
SIZE = {"mm": 1.0, "um": 1e-3, "m": 1e3, "m/s**2": 1e3, "rad": 1.0, "mrad": 1e-3,
        "deg": math.pi / 180, "1": 1.0, "": 1.0}


@dataclasses.dataclass
class Case:
    problem: Problem
    result: dict
    result_path: Path
    data: np.ndarray  # n_u × N: all the problem's columns


def _case(path: Path, tmp: Path) -> Case:
    problem = symcal.load_problem(path)
    result = symcal.solve(problem)
    assert result.success
    doc = json.loads(json.dumps(result.to_dict()))
    result_path = tmp / f"{problem.name}.result.json"
    result_path.write_text(json.dumps(doc), encoding="utf-8")
    data = load_datasets(problem, names=["calibration"])["calibration"]
    return Case(problem, doc, result_path, data.matrix(problem.columns))


@pytest.fixture(scope="module")
def platen(tmp_path_factory) -> Case:
    return _case(PLATEN, tmp_path_factory.mktemp("platen"))


@pytest.fixture(scope="module")
def dual(tmp_path_factory) -> Case:
    return _case(DUAL, tmp_path_factory.mktemp("dual"))


#: An accelerometer on a tilt table, in the units a user writes: m/s**2 and degrees.
G0 = 9.80665
ACCEL_MODEL = """\
model: accel
doc: one accelerometer axis, read in m/s**2
constants:
  g0: {value: 9.80665, unit: m/s**2}
inputs:
  f: {unit: m/s**2, doc: raw specific force}
parameters:
  bias: {value: 0, unit: m/s**2, scale: 0.1, doc: zero offset}
  gain: {value: 0, unit: "1", scale: 0.01, doc: scale factor error}
outputs:
  a: {expr: (f - bias) / (1 + gain), unit: m/s**2, doc: calibrated specific force}
  tilt: {expr: asin((f - bias) / (1 + gain) / g0), unit: deg, doc: tilt from level}
"""
ACCEL_PROBLEM = """\
problem: accel_tilt
doc: an accelerometer on a tilt table
constants:
  g0: {value: 9.80665, unit: m/s**2}
columns:
  t: {unit: s, role: time, doc: time}
  f_x: {unit: m/s**2, doc: raw reading of the accelerometer}
  tilt_ref: {unit: deg, doc: tilt of the table}
instances:
  ax: {model: accel.yaml, inputs: {f: f_x}, doc: the x axis}
constraints:
  g_a: {expr: ax.a - g0*sin(tilt_ref), unit: m/s**2, sigma: 0.01, doc: it reads gravity}
  g_tilt: {expr: ax.tilt - tilt_ref, unit: mrad, sigma: 1, doc: it finds the tilt}
datasets:
  calibration: {path: data.csv}
"""


@pytest.fixture(scope="module")
def accel(tmp_path_factory) -> Case:
    folder = tmp_path_factory.mktemp("accel")
    (folder / "accel.yaml").write_text(ACCEL_MODEL, encoding="utf-8")
    (folder / "accel_tilt.yaml").write_text(ACCEL_PROBLEM, encoding="utf-8")
    rng = np.random.default_rng(1)
    tilt = rng.uniform(-70, 70, N_OBS)
    f = G0 * np.sin(np.radians(tilt)) * 1.02 + 0.15 + rng.normal(0, 0.01, N_OBS)
    np.savetxt(folder / "data.csv", np.column_stack([np.arange(N_OBS) * 0.1, f, tilt]),
               delimiter=",", header="t,f_x,tilt_ref", comments="", fmt="%.17g")
    return _case(folder / "accel_tilt.yaml", folder)


def _theta(case: Case) -> np.ndarray:
    values = {p["name"]: p["value"] for p in case.result["parameters"]}
    return np.array([values[n] for n in case.problem.parameter_names])


def _reference(case: Case, theta: np.ndarray, u: np.ndarray) -> np.ndarray:
    """symcal's Python evaluation, one row per observation, in the driver's order, in
    internal units."""
    problem = case.problem
    g = ca.vertcat(*(c.sx for c in problem.constraints))
    signals = {s.name: s.sx for s in problem.signals}
    plan = codegen.plan(problem)
    outputs = [signals[o.name] for inst in plan.instances for o in inst.outputs]
    fn = mapped(problem.theta, problem.u,
                [g, ca.jacobian(g, problem.theta).T, ca.vertcat(*outputs)], "reference")
    return np.hstack(fn(theta, u))


def _sizes(plan: codegen.Plan) -> np.ndarray:
    """Per value of the driver's row (residuals, Jacobian row by row, outputs): the size
    of the unit the C returns it in (a Jacobian entry: its residual's unit per its
    parameter's declared unit, the parameter being in that unit already)."""
    residuals = [SIZE[c.unit] for c in plan.residuals]
    jacobian = [SIZE[c.unit] for c in plan.residuals for _ in plan.params]
    outputs = [SIZE[o.unit] for inst in plan.instances for o in inst.outputs]
    return np.array(residuals + jacobian + outputs)


def _driver(plan: codegen.Plan, u: np.ndarray, theta: np.ndarray | None) -> str:
    """A C program that prints, per observation, g, dg_dtheta row by row and the outputs."""
    p = plan.prefix
    rows = ",\n".join("    {" + ", ".join(repr(float(v)) for v in col) + "}" for col in u.T)
    params = "&params, " if theta is not None else ""
    lines = ["#include <stdio.h>", f'#include "{p}.h"',
             f"static const double data[{u.shape[1]}][{u.shape[0]}] = {{", rows, "};",
             "static void put(double v) { printf(\" %.17g\", v); }",
             "int main(void)", "{", "    int k, i, j;",
             f"    for (k = 0; k < {u.shape[1]}; ++k) {{",
             f"        {p}_input in;", f"        {p}_residuals r;"]
    lines += [f"        {p}_outputs_{inst.c} y_{inst.c};" for inst in plan.instances]
    if theta is not None:
        lines.append(f"        {p}_params params;")
        lines += [f"        params.{c.c} = {float(v)!r};"
                  for c, v in zip(plan.params, theta, strict=True)]
    lines += [f"        in.{c.c} = data[k][{i}];" for i, c in enumerate(plan.inputs)]
    lines += [f"        if ({p}_eval_residuals(&in, {params}&r) != 0) return 1;"]
    lines += [f"        if ({p}_eval_outputs_{inst.c}(&in, {params}&y_{inst.c}) != 0) return 1;"
              for inst in plan.instances]
    lines += [f"        put(r.{c.c});" for c in plan.residuals]
    lines += [f"        for (i = 0; i < {len(plan.residuals)}; ++i)",
              f"            for (j = 0; j < {len(plan.params)}; ++j) put(r.dg_dtheta[i][j]);"]
    lines += [f"        put(y_{inst.c}.{o.c});" for inst in plan.instances for o in inst.outputs]
    lines += ['        printf("\\n");', "    }", "    return 0;", "}", ""]
    return "\n".join(lines)


def _make(outdir: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items()
           if k not in ("CFLAGS", "CPPFLAGS", "LDFLAGS", "LDLIBS", "MAKEFLAGS")}
    return subprocess.run(["make", "-C", str(outdir), *args], capture_output=True, text=True,
                          env=env, timeout=120)


def _run_driver(plan: codegen.Plan, outdir: Path, u: np.ndarray,
                theta: np.ndarray | None) -> np.ndarray:
    src = outdir / "driver.c"
    src.write_text(_driver(plan, u, theta), encoding="utf-8")
    exe = outdir / "driver"
    build = subprocess.run(
        [CC, *STRICT, "-I", str(outdir), "-o", str(exe), str(src),
         str(outdir / f"{plan.prefix}.c"), str(outdir / f"{plan.prefix}_casadi.c"), "-lm"],
        capture_output=True, text=True, timeout=120)
    assert build.returncode == 0, build.stderr
    assert build.stderr == ""
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    return np.array([[float(v) for v in line.split()] for line in run.stdout.splitlines()])


def _assert_close(c: np.ndarray, py: np.ndarray, sizes: np.ndarray) -> None:
    """C values (declared units) against Python's (internal units)."""
    assert c.shape == py.shape
    want = py / sizes
    tol = RTOL * np.maximum(np.abs(want), 1.0 / sizes)
    worst = np.unravel_index(np.argmax(np.abs(c - want) / tol), c.shape)
    assert np.all(np.abs(c - want) <= tol), (
        f"C {c[worst]!r} vs Python {want[worst]!r} at observation {worst[0]}, value "
        f"{worst[1]}")


def _check_against_python(case: Case, outdir: Path, baked: bool) -> None:
    theta = _theta(case)
    plan = codegen.plan(case.problem, case.result_path if baked else None)
    u = case.data[:, :N_OBS]
    index = {c: i for i, c in enumerate(case.problem.columns)}
    c_values = _run_driver(plan, outdir, u[[index[c.name] for c in plan.inputs]],
                           None if baked else theta)
    py = _reference(case, theta, u)
    _assert_close(c_values, py, _sizes(plan))
    assert np.abs(py[:, :len(plan.residuals)]).max() > 1e-4  # residuals really evaluated


def _parse_example(stdout: str) -> tuple[str, dict[str, tuple[float, str]]]:
    hashes = re.findall(r"^hash (\w+)$", stdout, re.MULTILINE)
    values = {f"{kind} {name}": (float(v), unit) for kind, name, v, unit in
              re.findall(r"^(input|output|residual)\s+(\S+) = (\S+) ?(\S*)$", stdout,
                         re.MULTILINE)}
    assert len(hashes) == 1
    return hashes[0], values


def _check_example(case: Case, outdir: Path, theta: np.ndarray, baked: bool) -> None:
    """``make`` builds the example warning-free; it prints the hash and Python's values,
    each in the unit it names."""
    build = _make(outdir)
    assert build.returncode == 0, build.stderr
    assert "warning" not in build.stderr.lower(), build.stderr
    run = subprocess.run([str(outdir / "example")], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    digest, values = _parse_example(run.stdout)
    plan = codegen.plan(case.problem, case.result_path if baked else None)
    assert digest == plan.hash
    assert re.fullmatch(r"[0-9a-f]{16}", digest)
    u = case.data[:, :1]
    py = _reference(case, theta, u)[0]
    n_res, n_par = len(plan.residuals), len(plan.params)
    # symcal's values in internal units, converted; the inputs are in their units already
    expected = {f"residual {c.name}": (py[i] / SIZE[c.unit], c.unit)
                for i, c in enumerate(plan.residuals)}
    outs = [o for inst in plan.instances for o in inst.outputs]
    expected |= {f"output {o.name}": (py[n_res * (1 + n_par) + i] / SIZE[o.unit], o.unit)
                 for i, o in enumerate(outs)}
    index = {c: i for i, c in enumerate(case.problem.columns)}
    expected |= {f"input {c.name}": (u[index[c.name], 0], c.unit) for c in plan.inputs}
    assert set(values) == set(expected)
    for key, (want, unit) in expected.items():
        value, printed = values[key]
        assert printed == unit, key
        assert abs(value - want) <= RTOL * max(abs(want), 1.0 / SIZE[unit]), key


# ----------------------------------------------------------------------- compiled


@needs_cc
@pytest.mark.slow
def test_dual_baked_matches_python_and_example_runs(dual, tmp_path) -> None:
    out = tmp_path / "c"
    written = codegen.generate(dual.problem, out, dual.result_path)
    prefix = "symcal_dual_sensor_calibration"
    assert sorted(f.name for f in written) == sorted(
        [f"{prefix}_casadi.c", f"{prefix}_casadi.h", f"{prefix}.h", f"{prefix}.c", "main.c",
         "Makefile"])
    header = (out / f"{prefix}.h").read_text(encoding="utf-8")
    assert "double p1;  /* mm: raw reading of platen segment 1 (x) */" in header
    assert "double g_x;  /* um: the two sensors agree on the position along x (eq. 11) */" \
        in header  # the constraint's declared unit
    assert (f"double dg_dtheta[{prefix.upper()}_N_RESIDUALS][{prefix.upper()}_N_PARAMS];"
            in header)
    assert f"int {prefix}_eval_outputs_s1(const {prefix}_input *in, " \
           f"{prefix}_outputs_s1 *out);" in header
    assert f"{prefix}_params" not in header.replace(f"{prefix}_param_", "")  # baked
    assert "static" not in (out / f"{prefix}.c").read_text(encoding="utf-8")
    _check_against_python(dual, out, baked=True)
    _check_example(dual, out, _theta(dual), baked=True)


@pytest.mark.slow
@needs_cc
def test_platen_baked_and_unbaked_match_python(platen, tmp_path) -> None:
    baked_dir, free_dir = tmp_path / "baked", tmp_path / "free"
    codegen.generate(platen.problem, baked_dir, platen.result)  # the result as a dict
    codegen.generate(platen.problem, free_dir)
    _check_against_python(platen, baked_dir, baked=True)
    _check_against_python(platen, free_dir, baked=False)
    _check_example(platen, baked_dir, _theta(platen), baked=True)
    initial = np.array([p.value for p in platen.problem.parameters])
    _check_example(platen, free_dir, initial, baked=False)
    text = (free_dir / "symcal_platen_self_calibration.h").read_text(encoding="utf-8")
    assert "double s1_k3;  /* mm: sine of the 2nd harmonic ('s1.k3') */" in text
    assert ("int symcal_platen_self_calibration_eval_residuals(const "
            "symcal_platen_self_calibration_input *in, const symcal_platen_self_calibration_"
            "params *params, symcal_platen_self_calibration_residuals *out);") in text


def _flat(text: str) -> str:
    """A header's text with its comment leaders and line breaks as single spaces."""
    return " ".join(text.replace("\n *", "\n").split())


@needs_cc
def test_accelerometer_takes_and_returns_its_declared_units(accel, tmp_path) -> None:
    baked_dir, free_dir = tmp_path / "baked", tmp_path / "free"
    codegen.generate(accel.problem, baked_dir, accel.result_path)
    codegen.generate(accel.problem, free_dir)
    header = (free_dir / "symcal_accel_tilt.h").read_text(encoding="utf-8")
    for field in ["double f_x;  /* m/s**2: raw reading of the accelerometer */",
                  "double tilt_ref;  /* deg: tilt of the table */",
                  "double ax_bias;  /* m/s**2: zero offset ('ax.bias') */",
                  "double ax_gain;  /* 1: scale factor error ('ax.gain') */",
                  "double g_a;  /* m/s**2: it reads gravity */",
                  "double g_tilt;  /* mrad: it finds the tilt */",
                  "double a;  /* m/s**2: calibrated specific force */",
                  "double tilt;  /* deg: tilt from level */"]:
        assert field in header, field
    flat = _flat(header)
    assert ("The residuals and dg_dtheta of one observation. Takes in: f_x in m/s**2, "
            "tilt_ref in deg; params: theta, each in its parameter's unit (the fields of "
            "symcal_accel_tilt_params). Returns out: g_a in m/s**2, g_tilt in mrad; "
            "dg_dtheta in each residual's unit per each parameter's unit.") in flat
    assert ("The outputs of 'ax' of one observation. Takes in: f_x in m/s**2; params: "
            "theta, each in its parameter's unit (the fields of symcal_accel_tilt_params). "
            "Returns out: ax.a in m/s**2, ax.tilt in deg.") in flat
    _check_against_python(accel, baked_dir, baked=True)
    _check_against_python(accel, free_dir, baked=False)
    _check_example(accel, baked_dir, _theta(accel), baked=True)

    # against numpy, without symcal: the C in m/s**2, deg and mrad, to RTOL relative
    bias, gain = _theta(accel)
    index = {c: i for i, c in enumerate(accel.problem.columns)}
    f, tilt_ref = accel.data[index["f_x"]], accel.data[index["tilt_ref"]]
    plan = codegen.plan(accel.problem, accel.result_path)
    assert [c.name for c in plan.inputs] == ["f_x", "tilt_ref"]
    assert [c.name for c in plan.params] == ["ax.bias", "ax.gain"]
    c = _run_driver(plan, baked_dir, np.vstack([f, tilt_ref]), None)
    a = (f - bias) / (1 + gain)
    slope = 1 / np.sqrt(1 - (a / G0) ** 2) / G0 * 1e3  # d tilt [mrad] / d a [m/s**2]
    numpy = np.column_stack([
        a - G0 * np.sin(np.radians(tilt_ref)),                   # g_a [m/s**2]
        (np.arcsin(a / G0) - np.radians(tilt_ref)) * 1e3,        # g_tilt [mrad]
        np.full_like(a, -1 / (1 + gain)), -a / (1 + gain),       # d g_a / d bias, d gain
        -slope / (1 + gain), -slope * a / (1 + gain),            # d g_tilt / d bias, d gain
        a, np.degrees(np.arcsin(a / G0))])                       # ax.a [m/s**2], ax.tilt [deg]
    # each value to RTOL of the size of the terms it is a difference of
    terms = np.column_stack([np.full_like(a, G0), np.full_like(a, 1e3), np.abs(numpy[:, 2:])])
    assert np.all(np.abs(c - numpy) <= RTOL * terms), np.max(np.abs(c - numpy) / terms)
    # the residuals at the noise (0.01 m/s**2, about 1 mrad of tilt): the units are right
    assert 0.005 < np.std(c[:, 0]) < 0.02 and 0.5 < np.std(c[:, 1]) < 5


def test_hash_covers_the_yaml_and_the_baked_values(platen) -> None:
    problem = platen.problem
    free = codegen.plan(problem).hash
    baked = codegen.plan(problem, platen.result).hash
    changed = json.loads(json.dumps(platen.result))
    changed["parameters"][3]["value"] += 1e-15
    assert len({free, baked, codegen.plan(problem, changed).hash}) == 3
    assert codegen.plan(problem, platen.result_path).hash == baked


# ------------------------------------------------------------------------- errors


@pytest.mark.slow
def test_result_for_another_problem_is_refused(platen, dual, tmp_path) -> None:
    with pytest.raises(symcal.SymcalError) as err:
        codegen.generate(dual.problem, tmp_path / "c", platen.result_path)
    assert str(err.value) == (f"result file {platen.result_path} is for problem "
                              "'platen_self_calibration', not 'dual_sensor_calibration'")
    assert not (tmp_path / "c").exists()


def test_result_without_a_parameter_is_refused(platen, tmp_path) -> None:
    doc = json.loads(json.dumps(platen.result))
    doc["parameters"] = [p for p in doc["parameters"] if p["name"] != "s1.k3"]
    path = tmp_path / "result.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(symcal.SymcalError) as err:
        codegen.generate(platen.problem, tmp_path / "c", path)
    assert str(err.value) == f"result file {path} has no value for parameter 's1.k3'"


def test_result_with_an_unknown_parameter_or_a_failed_solve_is_refused(platen) -> None:
    doc = json.loads(json.dumps(platen.result))
    doc["parameters"].append({"name": "s9.k1", "value": 0.0})
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == ("the result has a value for parameter 's9.k1', which problem "
                              "'platen_self_calibration' does not have")
    doc = json.loads(json.dumps(platen.result))
    doc["solver"]["success"] = False
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == ("the result says its solve failed but its stages say it "
                              "succeeded; write it again with 'symcal solve PROBLEM --out "
                              "DIR'")
    doc["stages"][-1]["success"] = False
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == ("the result is from a failed solve; symcal exports only a "
                              "successful calibration (or none: omit --result to pass the "
                              "parameters at run time)")


def test_a_result_with_a_non_finite_or_damaged_entry_is_refused(platen) -> None:
    doc = json.loads(json.dumps(platen.result))
    doc["parameters"][0]["value"] = None  # what result.json holds for NaN
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == ("the result: parameter 's1.k0' has the value nan, not a finite "
                              "number")
    doc = json.loads(json.dumps(platen.result))
    doc["parameters"][0]["value"] = "0.1"
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == "the result: parameter 's1.k0' has the value 0.1, not a number"
    doc = json.loads(json.dumps(platen.result))
    del doc["stages"][0]["method"]
    with pytest.raises(symcal.SymcalError) as err:
        codegen.plan(platen.problem, doc)
    assert str(err.value) == ("the result is damaged or incomplete (no 'method'); write it "
                              "again with 'symcal solve PROBLEM --out DIR'")


MODEL = """\
model: {name}
inputs: {{p: {{unit: mm, doc: raw reading}}}}
parameters: {{{param}: {{value: 0.1, unit: mm}}}}
outputs: {{y: {{expr: p + {param}, unit: mm, doc: calibrated reading}}}}
"""
PROBLEM = """\
problem: collide
instances:
  s1: {model: a.yaml, inputs: {p: p1}}
  s1_p: {model: b.yaml, inputs: {p: p2}}
constraints:
  g: s1.y - s1_p.y
datasets:
  calibration: {path: data.csv}
columns: courier
"""


def test_names_that_collide_in_c_are_refused(tmp_path) -> None:
    (tmp_path / "a.yaml").write_text(MODEL.format(name="a", param="p_hat"), encoding="utf-8")
    (tmp_path / "b.yaml").write_text(MODEL.format(name="b", param="hat"), encoding="utf-8")
    (tmp_path / "collide.yaml").write_text(PROBLEM, encoding="utf-8")
    problem = symcal.load_problem(tmp_path / "collide.yaml")
    with pytest.raises(symcal.SymcalError) as err:
        codegen.generate(problem, tmp_path / "c")
    assert str(err.value) == ("cannot export: 's1.p_hat' and 's1_p.hat' both become the C "
                              "name 's1_p_hat'")


def test_a_function_without_c_translation_is_refused(platen, tmp_path) -> None:
    problem = platen.problem
    g = problem.constraints[0]
    bad = dataclasses.replace(problem, constraints=(
        Quantity(g.name, ca.erfinv(g.sx), g.unit, g.sigma, g.doc),))
    with pytest.raises(symcal.SymcalError) as err:
        codegen.generate(bad, tmp_path / "c")
    assert str(err.value) == ("cannot export constraint 'g_p': it uses the function 'erfinv' "
                              "which has no C translation")


HOSTILE_MODEL = """\
model: seg
doc: "ends a comment */ #error model ??/"
inputs: {p: {unit: mm, doc: "raw */ #error input ??="}}
parameters: {k: {value: 0.1, unit: mm, doc: "*/ #error parameter \\\\"}}
outputs: {y: {expr: p + k, unit: um, doc: "/* nested */ #error output"}}
"""
HOSTILE_PROBLEM = """\
problem: hostile
doc: "a problem */ #error problem ??/"
instances:
  s1: {model: seg.yaml, inputs: {p: p1}, doc: "*/ #error instance"}
  s2: {model: seg.yaml, inputs: {p: p2}}
constraints:
  g: {expr: s1.y - s2.y, unit: um, doc: "*/ #error constraint"}
datasets:
  calibration: {path: data.csv}
columns: courier
"""


@needs_cc
def test_text_from_the_yaml_stays_in_comments_and_strings(tmp_path) -> None:
    (tmp_path / "seg.yaml").write_text(HOSTILE_MODEL, encoding="utf-8")
    (tmp_path / "hostile.yaml").write_text(HOSTILE_PROBLEM, encoding="utf-8")
    problem = symcal.load_problem(tmp_path / "hostile.yaml")
    out = tmp_path / "c\\"  # a folder whose name ends in a backslash
    codegen.generate(problem, out)
    for name in ("symcal_hostile.c", "main.c"):
        build = subprocess.run([CC, *STRICT, "-c", "-I", str(out), "-o", os.devnull,
                                str(out / name)], capture_output=True, text=True, timeout=120)
        assert build.returncode == 0 and build.stderr == "", build.stderr
    header = (out / "symcal_hostile.h").read_text(encoding="utf-8")
    assert "#error" in header and "*/ #error" not in header
    dry = _make(out, "-n")  # the Makefile's comment does not swallow its first rule
    assert dry.returncode == 0 and "-std=c99" in dry.stdout, dry.stdout + dry.stderr


def test_another_target_is_a_template_set(platen, tmp_path) -> None:
    folder = tmp_path / "templates"
    folder.mkdir()
    (folder / "units.csv.j2").write_text(
        "name,unit\n{% for inst in instances %}{% for c in inst.outputs %}"
        "{{ c.name }},{{ c.unit }}\n{% endfor %}{% endfor %}"
        "{% for c in residuals %}{{ c.name }},{{ c.unit }}\n{% endfor %}", encoding="utf-8")
    target = render.Target("csv", (("units.csv.j2", "{prefix}_units.csv"),), folder)
    written = codegen.generate(platen.problem, tmp_path / "out", target=target)
    prefix = "symcal_platen_self_calibration"
    assert [f.name for f in written] == [f"{prefix}_casadi.c", f"{prefix}_casadi.h",
                                         f"{prefix}_units.csv"]
    lines = (tmp_path / "out" / f"{prefix}_units.csv").read_text(encoding="utf-8").split()
    assert lines[0] == "name,unit" and lines[1] == "s1.p_hat,mm" and lines[-1] == "g_p,um"
    with pytest.raises(symcal.SymcalError) as err:
        codegen.generate(platen.problem, tmp_path / "other", target="rust")
    assert str(err.value) == ("no code generation target 'rust'; symcal has c (or give a "
                              "Target of your own templates)")


def test_templates_ship_as_package_data() -> None:
    """Every template is named by pyproject's package data (a wheel carries it: checked by
    hand with 'pip install .' into another folder) and used by its target, and
    importlib.resources finds it where the package is."""
    import importlib.resources

    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    globs = pyproject["tool"]["setuptools"]["package-data"]["symcal.export"]
    folder = ROOT / "symcal" / "export"
    present = {p.relative_to(folder).as_posix() for p in (folder / "templates").rglob("*")
               if p.is_file() and "__pycache__" not in p.parts}
    shipped = {p.relative_to(folder).as_posix() for g in globs for p in folder.glob(g)}
    used = {f"templates/{t.name}/{template}" for t in render.TARGETS.values()
            for template, _ in t.files}
    assert present and present == shipped == used
    package = importlib.resources.files("symcal.export")
    assert all(package.joinpath(*path.split("/")).is_file() for path in used)


def test_c_identifiers() -> None:
    assert codegen.c_identifier("s1.k3") == "s1_k3"
    assert codegen.c_identifier("int") == "int_"
    assert codegen.c_identifier("errno") == "errno_"
    assert codegen.c_identifier("9lives") == "_9lives"
    assert codegen.c_identifier("a-b c") == "a_b_c"


# ---------------------------------------------------------------------------- CLI


def test_cli_writes_the_files_and_reports_errors(platen, tmp_path, capsys) -> None:
    parser = argparse.ArgumentParser(prog="symcal")
    cli_codegen.add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "c"
    args = parser.parse_args(["codegen", str(PLATEN), "--result", str(platen.result_path),
                              "-o", str(out)])
    assert cli_codegen.run(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"wrote {out / 'symcal_platen_self_calibration_casadi.c'}"
    assert lines[-1] == f"wrote {out / 'Makefile'}"
    assert len(lines) == 6
    args = parser.parse_args(["codegen", str(PLATEN), "--result",
                              str(tmp_path / "missing.json"), "-o", str(out)])
    with pytest.raises(symcal.SymcalError,
                       match=r"result file .*missing\.json not found"):
        cli_codegen.run(args)
