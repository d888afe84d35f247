"""C export: the generated code compiles warning-free and agrees with symcal's Python.

The generated functions are compiled with the system C compiler and evaluated on the
first N_OBS observations of each problem's calibration dataset; every residual, every
entry of the Jacobian and every instance output must agree with symcal's own evaluation
of the problem's SX (``symcal.base.numeric.mapped``) to RTOL relative.  Values below 1 in
symcal's internal units (mm, rad) are held to RTOL absolute instead: the residuals are
differences of readings of order 1-100 mm, so their rounding is relative to those.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shutil
import subprocess
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
from symcal.problem.symbolic import Problem, Quantity

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"
CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler ('cc' or 'gcc') on PATH")
N_OBS = 200
RTOL = 1e-12
#: The test driver is built with every warning an error; -O0 keeps compiling fast.
STRICT = ["-std=c99", "-O0", "-Wall", "-Wextra", "-Werror", "-pedantic"]


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


def _theta(case: Case) -> np.ndarray:
    values = {p["name"]: p["value"] for p in case.result["parameters"]}
    return np.array([values[n] for n in case.problem.parameter_names])


def _reference(case: Case, theta: np.ndarray, u: np.ndarray) -> np.ndarray:
    """symcal's Python evaluation, one row per observation, in the driver's order."""
    problem = case.problem
    g = ca.vertcat(*(c.sx for c in problem.constraints))
    signals = {s.name: s.sx for s in problem.signals}
    plan = codegen.plan(problem)
    outputs = [signals[o.name] for inst in plan.instances for o in inst.outputs]
    fn = mapped(problem.theta, problem.u,
                [g, ca.jacobian(g, problem.theta).T, ca.vertcat(*outputs)], "reference")
    return np.hstack(fn(theta, u))


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


def _assert_close(c: np.ndarray, py: np.ndarray) -> None:
    assert c.shape == py.shape
    tol = RTOL * np.maximum(np.abs(py), 1.0)
    worst = np.unravel_index(np.argmax(np.abs(c - py) / tol), c.shape)
    assert np.all(np.abs(c - py) <= tol), (
        f"C {c[worst]!r} vs Python {py[worst]!r} at observation {worst[0]}, value {worst[1]}")


def _check_against_python(case: Case, outdir: Path, baked: bool) -> None:
    theta = _theta(case)
    plan = codegen.plan(case.problem, case.result_path if baked else None)
    u = case.data[:, :N_OBS]
    index = {c: i for i, c in enumerate(case.problem.columns)}
    c_values = _run_driver(plan, outdir, u[[index[c.name] for c in plan.inputs]],
                           None if baked else theta)
    py = _reference(case, theta, u)
    _assert_close(c_values, py)
    assert np.abs(py[:, :len(plan.residuals)]).max() > 1e-4  # residuals really evaluated


def _parse_example(stdout: str) -> tuple[str, dict[str, float]]:
    hashes = re.findall(r"^hash (\w+)$", stdout, re.MULTILINE)
    values = {f"{kind} {name}": float(v) for kind, name, v in
              re.findall(r"^(input|output|residual)\s+(\S+) = (\S+)", stdout, re.MULTILINE)}
    assert len(hashes) == 1
    return hashes[0], values


def _check_example(case: Case, outdir: Path, theta: np.ndarray, baked: bool) -> None:
    """``make`` builds the example warning-free; it prints the hash and Python's values."""
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
    expected = {f"residual {c.name}": py[i] for i, c in enumerate(plan.residuals)}
    outs = [o.name for inst in plan.instances for o in inst.outputs]
    expected |= {f"output {n}": py[n_res * (1 + n_par) + i] for i, n in enumerate(outs)}
    index = {c: i for i, c in enumerate(case.problem.columns)}
    expected |= {f"input {c.name}": u[index[c.name], 0] for c in plan.inputs}
    assert set(values) == set(expected)
    for key, want in expected.items():
        assert abs(values[key] - want) <= RTOL * max(abs(want), 1.0), key


# ----------------------------------------------------------------------- compiled


@needs_cc
def test_dual_baked_matches_python_and_example_runs(dual, tmp_path) -> None:
    out = tmp_path / "c"
    written = codegen.generate(dual.problem, out, dual.result_path)
    prefix = "symcal_dual_sensor_calibration"
    assert sorted(f.name for f in written) == sorted(
        [f"{prefix}_casadi.c", f"{prefix}_casadi.h", f"{prefix}.h", f"{prefix}.c", "main.c",
         "Makefile"])
    header = (out / f"{prefix}.h").read_text(encoding="utf-8")
    assert "double p1;  /* mm: raw reading of platen segment 1 (x) */" in header
    assert "double g_x;  /* mm: the two sensors agree on the position along x" in header
    assert (f"double dg_dtheta[{prefix.upper()}_N_RESIDUALS][{prefix.upper()}_N_PARAMS];"
            in header)
    assert f"int {prefix}_eval_outputs_s1(const {prefix}_input *in, " \
           f"{prefix}_outputs_s1 *out);" in header
    assert f"{prefix}_params" not in header.replace(f"{prefix}_param_", "")  # baked
    assert "static" not in (out / f"{prefix}.c").read_text(encoding="utf-8")
    _check_against_python(dual, out, baked=True)
    _check_example(dual, out, _theta(dual), baked=True)


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


def test_hash_covers_the_yaml_and_the_baked_values(platen) -> None:
    problem = platen.problem
    free = codegen.plan(problem).hash
    baked = codegen.plan(problem, platen.result).hash
    changed = json.loads(json.dumps(platen.result))
    changed["parameters"][3]["value"] += 1e-15
    assert len({free, baked, codegen.plan(problem, changed).hash}) == 3
    assert codegen.plan(problem, platen.result_path).hash == baked


# ------------------------------------------------------------------------- errors


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
    with pytest.raises(symcal.SymcalError, match="is from a failed solve"):
        codegen.plan(platen.problem, doc)


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
