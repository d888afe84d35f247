"""The worked example examples/hidden_effect runs exactly as its README says."""

from __future__ import annotations

import re

import pytest
from conftest import ROOT

from symcal.cli import main

EXAMPLE = ROOT / "examples" / "hidden_effect"


def _run(capsys, *argv: str) -> str:
    assert main(list(argv)) == 0
    return capsys.readouterr().out


@pytest.mark.slow
def test_walkthrough(capsys, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(ROOT)
    readme = (EXAMPLE / "README.md").read_text()
    # 1. the basic model stays well above the noise floor
    out = _run(capsys, "solve", "examples/hidden_effect/problem.yaml", "--quiet")
    assert out == ""
    out = _run(capsys, "solve", "examples/hidden_effect/problem.yaml")
    g_p = float(re.search(r"calibration  g_p +\S+ +(\S+)", out).group(1))
    assert 1.7 < g_p < 2.2
    # the verdict states each dataset against its noise floor, as the README shows
    for line in ("  calibration: 1.94× the noise floor (χ²/dof 3.76, band 0.91–1.09)",
                 "  flyby: 1.97× the noise floor (χ²/dof 3.88, band 0.86–1.15)"):
        assert line in out.split("\n\n")[1].splitlines() and line in readme
    # 2. the diagnosis names the effect first, with the YAML the example ships
    plots = tmp_path / "plots"
    out = _run(capsys, "diagnose", "examples/hidden_effect/problem.yaml", "--quiet",
               "--plots", str(plots), "--report", str(tmp_path / "report.html"))
    table = re.search(r"^ +1  (.*)$", out, re.MULTILINE).group(1)
    assert table.startswith("s2.p_hat += harmonic 3 of s2.p (period 1.016 mm)")
    assert table.split()[0] + " " + " ".join(table.split()[1:9]) in readme
    shipped = (EXAMPLE / "models" / "platen_segment_p_hat_h3_p.yaml").read_text()
    suggested = out.split("To add it:\n", 1)[1].split("\n\n", 1)[0]
    suggested_lines = [ln[7:] for ln in suggested.splitlines()[1:]]
    assert "\n".join(suggested_lines) + "\n" == shipped
    overlay = out.split("# basic_s2_p_hat_h3_p.yaml (beside problem.yaml): the problem with it\n",
                        1)[1].split("\n\n", 1)[0]
    assert "\n".join(ln[7:] for ln in overlay.splitlines()) + "\n" == (
        EXAMPLE / "problem_revised.yaml").read_text()
    assert (plots / "candidates.png").stat().st_size > 0
    assert "<img" in (tmp_path / "report.html").read_text()
    # 4. the ladder shows the error falling to the noise floor
    out = _run(capsys, "compare", "examples/hidden_effect/problem.yaml",
               "examples/hidden_effect/problem_revised.yaml")
    rows = {ln.split("(")[0].strip(): ln.split()[-2:] for ln in out.splitlines()
            if "std" in ln or "AIC" in ln or "BIC" in ln}
    basic, revised = map(float, rows["calibration g_p std"])
    assert basic > 1.7 and abs(revised - 1.0) < 0.1
    fly_basic, fly_revised = map(float, rows["flyby g_p std"])
    assert fly_revised < 0.6 * fly_basic
    assert float(rows["BIC"][1]) < float(rows["BIC"][0]) - 100
    for line in ("BIC (calibration)                     1518.3                 133.7",
                 "calibration g_p std (µm)               1.928                0.9606",
                 "flyby g_p std (µm)                     2.083                 1.033"):
        assert line in out and line in readme
    # and nothing significant is left
    out = _run(capsys, "diagnose", "examples/hidden_effect/problem_revised.yaml", "--quiet")
    assert "no candidate effect is significant" in out
    assert ("where it fails: nowhere: every dataset is at its noise floor (calibration "
            "χ²/dof 0.93, band 0.91–1.09; flyby χ²/dof 0.958, band 0.86–1.15)") in out
    for text in ("at the noise floor (χ²/dof 0.93, band 0.91–1.09)",
                 "at the noise floor (χ²/dof 0.958, band 0.86–1.15)"):
        assert text in readme
