"""The planar-arm example (examples/planar_arm): closed-chain self-calibration of a pinned
3-link arm, outside the courier.  Its gauges are named when nothing is fixed, every
identifiable parameter is recovered once they are fixed, ``diagnose`` is quiet on clean
data and finds a planted encoder gain, the generated C compiles and matches numpy, and
the README's commands run as written."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.calibrate.result import StageResult
from symcal.cli import main
from symcal.revise.diagnose import diagnose

EXAMPLE = ROOT / "examples" / "planar_arm"
FREE = EXAMPLE / "problem.yaml"
FIXED = EXAMPLE / "problem_fixed.yaml"
CC = shutil.which("cc") or shutil.which("gcc")


def _simulator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("simulate_arm", EXAMPLE / "simulate_arm.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _simulate(out: Path, *args: str) -> dict:
    assert _simulator().main(["--out", str(out), *args]) == 0
    return json.loads((out / "truth.json").read_text())


def _data(folder: Path) -> dict[str, str]:
    return {"calibration": str(folder / "calibration.csv"),
            "validation": str(folder / "validation.csv")}


def _residuals(params: dict[str, float], q: np.ndarray) -> np.ndarray:
    """The constraints g_x, g_y (N × 2, m) by numpy's forward kinematics: independent of
    symcal's expression grammar."""
    offsets = np.array([params[f"e{i}.offset"] for i in (1, 2, 3)])
    c = np.cumsum(q + offsets[None, :], axis=1)
    a = np.array([params["a1"], params["a2"], params["a3"]])
    return np.column_stack([np.cos(c) @ a - params["px"], np.sin(c) @ a - params["py"]])


def _readings(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1)[:, 1:]


def test_simulator_writes_the_shipped_data(tmp_path) -> None:
    truth = _simulate(tmp_path, "--seed", "1")
    for name in ("calibration.csv", "validation.csv", "truth.json"):
        assert (tmp_path / name).read_text() == (EXAMPLE / "data" / name).read_text()
    # the readings put the tool on the pin, to the encoder noise
    g = _residuals(truth["parameters"], _readings(tmp_path / "calibration.csv"))
    assert 1e-6 < np.abs(g).max() < 1e-4


def test_gauges_named_when_nothing_is_fixed() -> None:
    result = symcal.solve(FREE)
    (stage,) = result.stages
    assert stage.gauges is not None
    scale, rotation = stage.gauges.gauges
    assert (scale.kind, scale.parameters, scale.degree) == (
        "scale", ("a1", "a2", "a3", "px", "py"), 1.0)
    assert scale.fix == "fix one of a1, a2, a3, px, py or give a known length"
    assert (rotation.kind, rotation.parameters) == ("rotation", ("e1.offset", "px", "py"))
    assert rotation.fix == "fix e1.offset or give a known direction"
    # the named gauges are real symmetries, checked with numpy at a random point
    rng = np.random.default_rng(3)
    q = _readings(EXAMPLE / "data" / "calibration.csv")
    theta = {n: v + 0.05 * rng.standard_normal() for n, v in
             json.loads((EXAMPLE / "data" / "truth.json").read_text())["parameters"].items()}
    g = _residuals(theta, q)
    scaled = {n: 1.7 * v if n in scale.parameters else v for n, v in theta.items()}
    np.testing.assert_allclose(_residuals(scaled, q), 1.7 * g, rtol=1e-12, atol=1e-15)
    alpha = 0.4
    turned = dict(theta)
    turned["e1.offset"] += alpha
    turned["px"] = np.cos(alpha) * theta["px"] - np.sin(alpha) * theta["py"]
    turned["py"] = np.sin(alpha) * theta["px"] + np.cos(alpha) * theta["py"]
    np.testing.assert_allclose(np.sum(_residuals(turned, q) ** 2, axis=1),
                               np.sum(g**2, axis=1), rtol=1e-10)
    # unfixed, the solve slides onto the scale's trivial point: a failed solve, saying why
    assert not result.success and stage.status == "Collapsed"
    assert stage.message.startswith("failed: the solve collapsed onto the trivial point of "
                                    "a gauge: a1, a2, a3, px, py all went to zero")
    assert stage.message.endswith(scale.fix)
    assert max(abs(result.params[n].value) for n in scale.parameters) < 1e-12
    # in --json, and back
    doc = json.loads(json.dumps(result.to_dict()))["stages"][0]
    assert [g["kind"] for g in doc["gauges"]["gauges"]] == ["scale", "rotation"]
    assert doc["gauges"]["gauges"][0]["generator"] == [[1.0, 0.0], [0.0, 1.0]]
    assert doc["gauges"]["gauges"][1]["generator"] == [[0.0, -1.0], [1.0, 0.0]]
    assert StageResult.from_dict(doc).gauges == stage.gauges
    # and the report says it before anything else
    text = symcal.text_report(result)
    assert "  2 gauge(s) found before the solve, which no data can determine (scale of a1, " \
           "a2, a3, px, py; rotation of e1.offset, px, py); see Gauges for the fix" in text


def test_an_exact_rotation_on_noisy_data_is_named(tmp_path) -> None:
    """With one length fixed, the base rotation stays: named on noisy data, not 'rank 7 of
    7' with correlations of ±1."""
    overlay = tmp_path / "one_length.yaml"
    overlay.write_text(f"problem: planar_arm_one_length\nextends: {FREE}\n"
                       "parameters:\n  a1: {value: 0.4012, unit: m, fixed: true}\n")
    result = symcal.solve(overlay)
    assert result.success
    ident = result.identifiability
    assert (ident.rank, ident.n_free) == (6, 7)
    (null,) = ident.null_space
    assert set(null.coefficients) == {"e1.offset", "px", "py"}
    # the direction is the rotation at the estimate: (1, -py, px)
    c = null.coefficients
    assert c["e1.offset"] == 1.0
    assert c["px"] == pytest.approx(-result.params["py"].value, rel=1e-3)
    assert c["py"] == pytest.approx(result.params["px"].value, rel=1e-3)
    assert all(result.uncertainty.se[n] is None for n in ("e1.offset", "px", "py"))
    corr = result.uncertainty.correlation
    finite = corr[np.isfinite(corr)]
    assert np.all(np.abs(finite[np.abs(finite) < 1 - 1e-12]) < 0.999)


@pytest.mark.parametrize("seed", [1, 2])
def test_recovery_within_three_standard_errors(seed, tmp_path) -> None:
    if seed == 1:
        folder = EXAMPLE / "data"
        truth = json.loads((folder / "truth.json").read_text())
    else:
        folder = tmp_path
        truth = _simulate(folder, "--seed", str(seed))
    result = symcal.solve(FIXED, _data(folder))
    assert result.success
    assert (result.identifiability.rank, result.identifiability.n_free) == (6, 6)
    assert not result.stages[-1].gauges.gauges
    expected = truth["gauge_fixed"]
    for p in result.params.values():
        if p.fixed:
            assert p.value == expected[p.name]
            continue
        assert p.se is not None and 0 < p.se < 1e-4
        assert abs(p.value - expected[p.name]) < 3 * p.se, (p.name, p.value, p.se)
    # the gauge-free parameters are the truth itself
    for name in ("a2", "a3", "e2.offset", "e3.offset"):
        assert expected[name] == truth["parameters"][name]


def test_noiseless_data_are_solved_to_the_digits_the_files_keep(tmp_path) -> None:
    """Noiseless readings (rounded to the 10 digits of the CSV): a success, not a stall,
    with every parameter at the truth to the rounding of the readings; the nothing-fixed
    problem still names both gauges."""
    truth = _simulate(tmp_path, "--seed", "3", "--noise", "0")
    result = symcal.solve(FIXED, _data(tmp_path))
    assert result.success, result.stages[-1].message
    expected = truth["gauge_fixed"]
    for p in result.params.values():
        assert abs(p.value - expected[p.name]) < 1e-8, (p.name, p.value, expected[p.name])
    free = symcal.solve(FREE, _data(tmp_path))
    assert {g.kind for g in free.stages[-1].gauges.gauges} >= {"scale", "rotation"}


@pytest.mark.slow
def test_diagnose_quiet_on_clean_data_and_finds_a_planted_gain(tmp_path) -> None:
    clean = diagnose(symcal.solve(FIXED))
    assert clean.significant == ()
    _simulate(tmp_path, "--seed", "1", "--gain", "e2=0.002")
    diag = diagnose(symcal.solve(FIXED, _data(tmp_path)))
    top = diag.significant[0]
    assert top.label == "e2.angle += a term linear in e2.q"
    # φ2 = (1 + gain)·q2 + offset: the term's coefficient is the gain
    assert top.coefficient[0] == pytest.approx(0.002, rel=0.05)


@pytest.mark.slow
@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_generated_c_compiles_and_matches_numpy(tmp_path) -> None:
    result = symcal.solve(FIXED)
    result.save(tmp_path / "result.json")
    out = tmp_path / "c"
    assert main(["codegen", str(FIXED), "--result", str(tmp_path / "result.json"), "-o",
                 str(out)]) == 0
    build = subprocess.run(["make", "-C", str(out)], capture_output=True, text=True,
                           timeout=120)
    assert build.returncode == 0 and "warning" not in build.stderr.lower(), build.stderr
    run = subprocess.run([str(out / "example")], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0
    printed = {m[0]: (float(m[1]), m[2]) for m in
               re.findall(r"^residual\s+(\S+) = (\S+) (\S+)$", run.stdout, re.MULTILINE)}
    assert set(printed) == {"g_x", "g_y"}
    q = _readings(EXAMPLE / "data" / "calibration.csv")[:1]
    expected = _residuals({n: p.value for n, p in result.params.items()}, q)[0]
    metres = {"m": 1.0, "mm": 1e-3, "um": 1e-6}
    for k, name in enumerate(("g_x", "g_y")):
        value, unit = printed[name]
        assert value * metres[unit] == pytest.approx(expected[k], rel=1e-9, abs=1e-15)


def _commands(readme: str) -> list[str]:
    blocks = re.findall(r"```sh\n(.*?)```", readme, re.DOTALL)
    return [ln for block in blocks for ln in block.splitlines() if ln.strip()]


@pytest.mark.slow
def test_the_readme_walkthrough_runs_as_written(tmp_path, monkeypatch, capsys) -> None:
    readme = (EXAMPLE / "README.md").read_text()
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    outputs = []
    for line in _commands(readme):
        argv = shlex.split(line)
        if argv[0] == "symcal":
            code = main(argv[1:])
            out = capsys.readouterr().out
            # only the solve with nothing fixed fails: it collapses onto the scale gauge
            assert code == (1 if argv[1:3] == ["solve", "examples/planar_arm/problem.yaml"]
                            else 0), line
        else:
            if argv[0] == "python":
                argv[0] = sys.executable
            if argv[0] == "make" and CC is None:
                break
            done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, (line, done.stderr)
            assert "warning" not in done.stderr.lower()
            out = done.stdout
        outputs.append((line, out))
    assert len(outputs) >= 7
    by_command = dict(outputs)
    # 0: the simulator writes what the example ships
    assert (tmp_path / "build/planar_arm/calibration.csv").read_text() == (
        EXAMPLE / "data" / "calibration.csv").read_text()
    # 1: the gauges block is printed as the README shows it
    gauges = readme.split("```text\n")[1].split("```")[0]
    assert gauges in by_command["symcal solve examples/planar_arm/problem.yaml"]
    failed = readme.split("```text\n")[2].split("```")[0].strip()
    head, tail = failed.split("...")
    out = by_command["symcal solve examples/planar_arm/problem.yaml"]
    assert re.search(re.escape(head) + r"\S+" + re.escape(tail), out)
    # 2: solved, rank 6 of 6, and the README's table is what was found
    out = next(o for c, o in outputs if "problem_fixed.yaml --out" in c)
    assert "rank 6 of 6 free parameters" in out
    # against the floor the encoders' declared noise sets, as the README says
    for line in ("calibration: at the noise floor (χ²/dof 0.903, band 0.87–1.14)",
                 "validation: at the noise floor (χ²/dof 1.19, band 0.81–1.21)"):
        assert f"  {line}" in out.splitlines()
        assert " ".join(line.split()) in " ".join(readme.replace("`", "").split())
    for row in re.findall(r"^\| (e\d\.offset|a\d|p[xy]) \| (\S+) (?:rad|m) \| (\S+) \|", readme,
                          re.MULTILINE):
        name, value, se = row
        line = next(ln for ln in out.splitlines() if ln.split()[:1] == [name])
        assert line.split()[1:3] == [value.replace("−", "-"), se], line
    # 3 and 4: quiet on clean data; the gain found
    diagnoses = [o for c, o in outputs if c.startswith("symcal diagnose")]
    assert "what to add: nothing significant (no candidate effect passes the test)" in \
        diagnoses[0]
    assert "what to add: e2.angle += a term linear in e2.q" in diagnoses[1]
    # 5: the example runs and prints the baked parameters' residuals
    if CC is not None:
        assert "residual  g_x = " in outputs[-1][1]
