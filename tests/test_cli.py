"""The command line: exit codes, messages without tracebacks, JSON, --data, --out."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, courier_data, write_csv

from symcal.cli import main

PROBLEM = str(ROOT / "problems" / "platen_self_calibration.yaml")


@pytest.fixture(scope="module")
def csvs(tmp_path_factory, ) -> tuple[Path, Path]:
    rng = np.random.default_rng(7)
    k = rng.normal(0, 0.003, (4, 9)) / np.array([1, 1, 1, 2, 2, 4, 4, 6, 6])
    d = tmp_path_factory.mktemp("data")
    return (write_csv(d / "cal.csv", courier_data(600, k, 5e-4, 1)),
            write_csv(d / "fly.csv", courier_data(200, k, 5e-4, 2)))


def _args(csvs) -> list[str]:
    return ["--data", f"calibration={csvs[0]}", "--data", f"flyby={csvs[1]}"]


def test_solve_json_document(csvs, capsys) -> None:
    assert main(["solve", PROBLEM, *_args(csvs), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["solver"]["method"] == "linear"
    assert doc["identifiability"]["rank"] == 33
    assert doc["identifiability"]["null_space"] == [
        "s1.k0 - s4.k0", "s2.k0 + s4.k0", "s3.k0 + s4.k0"]
    combos = doc["identifiability"]["identifiable_combinations"]
    assert combos[0]["combination"] == "s1.k0 - s2.k0 - s3.k0 + s4.k0"
    rows = {(s["dataset"], s["name"]): s for s in doc["statistics"]}
    assert set(rows) == {
        ("calibration", "g_p"), ("calibration", "theta_x"), ("calibration", "theta_y"),
        ("flyby", "g_p"), ("flyby", "theta_x"), ("flyby", "theta_y"), ("flyby", "position_y")}
    for key in (("calibration", "g_p"), ("flyby", "g_p")):
        assert rows[key]["unit"] == "um"
        assert rows[key]["after"]["rms"] < rows[key]["before"]["rms"]
    assert len(doc["parameters"]) == 36
    assert doc["datasets"][0] == {"name": "calibration", "source": str(csvs[0]), "n": 600,
                                  "dropped": 0, "file": str(Path(csvs[0]).resolve()),
                                  "sha256": hashlib.sha256(csvs[0].read_bytes()).hexdigest()}


def test_solve_text_report_and_out(csvs, tmp_path, capsys) -> None:
    out = tmp_path / "res"
    assert main(["solve", PROBLEM, *_args(csvs), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rank 33 of 36 free parameters" in text
    assert "s1.k0 - s2.k0 - s3.k0 + s4.k0 = " in text
    assert "g_p" in text and "position_y vs reference" in text
    assert json.loads((out / "result.json").read_text())["problem"] == "platen_self_calibration"
    assert (out / "report.txt").read_text() in text


def test_spec_error_exit_2_no_traceback(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    Path("bad.yaml").write_text("problem: x\ninstances: {}\nconstraint: {}\ndatasets: {}\n")
    assert main(["solve", "bad.yaml"]) == 2
    assert capsys.readouterr().err == (
        "symcal: error: bad.yaml:3: constraint: unknown key 'constraint' (did you mean "
        "'constraints'?); allowed keys: problem, constraints, datasets, instances, doc, "
        "extends, constants, parameters, columns, expressions, comparisons, stages, "
        "weighting, implicit, solver, noise, candidates\n")


def test_unknown_dataset_override(csvs, capsys) -> None:
    assert main(["solve", PROBLEM, "--data", f"calibraton={csvs[0]}"]) == 2
    assert capsys.readouterr().err == (
        "symcal: error: --data calibraton=...: the problem has no dataset 'calibraton' "
        "(did you mean 'calibration'?); it has: calibration, flyby\n")


def test_bad_data_option(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["solve", PROBLEM, "--data", "calibration"])
    assert exc.value.code == 2
    assert "expected NAME=PATH, found 'calibration'" in capsys.readouterr().err


def test_debug_shows_traceback(tmp_path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("problem: [\n")
    with pytest.raises(Exception, match="invalid YAML"):
        main(["--debug", "solve", str(bad)])


def test_python_dash_m(csvs) -> None:
    proc = subprocess.run([sys.executable, "-m", "symcal", "solve", PROBLEM, *_args(csvs),
                           "--quiet"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ""


def test_simulate_then_solve_on_the_files(tmp_path, capsys) -> None:
    scenario = str(ROOT / "problems" / "scenarios" / "courier_platen.yaml")
    out = tmp_path / "run.csv"
    assert main(["simulate", scenario, "-o", str(out), "--seed", "4", "-n", "300"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        f"wrote {tmp_path / 'run.calibration.csv'}", f"wrote {tmp_path / 'run.flyby.csv'}",
        f"wrote {tmp_path / 'run.truth.yaml'}"]
    import yaml

    truth = yaml.safe_load((tmp_path / "run.truth.yaml").read_text())
    assert truth["seed"] == 4 and truth["parameters"]["s1.k1"] == 0.017
    header = (tmp_path / "run.calibration.csv").read_text().splitlines()[0]
    assert header == "t,p1,p2,p3,p4,x_ref,y_ref,theta_ref"
    assert main(["solve", PROBLEM, "--json",
                 "--data", f"calibration={tmp_path}/run.calibration.csv",
                 "--data", f"flyby={tmp_path}/run.flyby.csv"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [d["n"] for d in doc["datasets"]] == [300, 300]


def test_simulate_single_run_and_unknown_run(tmp_path, capsys) -> None:
    scenario = str(ROOT / "problems" / "scenarios" / "courier_platen.yaml")
    assert main(["simulate", scenario, "-o", str(tmp_path / "c.csv"), "--run", "flyby",
                 "-n", "10"]) == 0
    assert (tmp_path / "c.csv").read_text().count("\n") == 11
    capsys.readouterr()
    assert main(["simulate", scenario, "-o", str(tmp_path / "c.csv"), "--run", "flyb"]) == 2
    assert "no run named 'flyb' (did you mean 'flyby'?)" in capsys.readouterr().err
