"""docs/python.md runs as written (issue 24 item 6): its Python blocks in order, in one
namespace, from the repository root; and what it says of --quiet is what it does."""

from __future__ import annotations

import re

import pytest
from conftest import ROOT

from symcal.cli import main

RECIPE = ROOT / "docs" / "python.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", RECIPE.read_text(), re.DOTALL)


@pytest.mark.slow
def test_the_python_recipe_runs_as_written(monkeypatch, capsys) -> None:
    monkeypatch.chdir(ROOT)
    namespace: dict[str, object] = {}
    blocks = _blocks()
    assert len(blocks) == 7
    for block in blocks:
        exec(compile(block, str(RECIPE), "exec"), namespace)  # noqa: S102 - our own doc
    out = capsys.readouterr().out
    assert "Verdict" in out and "b_z = 0.080" in out and "m/s**2" in out
    result = namespace["result"]
    assert namespace["stat"].unit == "mm/s**2"
    assert namespace["internal"][0] == pytest.approx(namespace["g_n"][0])   # mm/s^2 both
    assert namespace["f_z"][0] == pytest.approx(
        result.value("acc.fz", "validation")[0] * 100)                       # type: ignore[attr-defined]


def test_quiet_hides_the_report_of_a_success_only(capsys) -> None:
    """The recipe's last paragraph: --quiet prints nothing on success, the report on a
    failure."""
    fixed = ROOT / "examples" / "diff_drive" / "problem_fixed.yaml"
    assert main(["solve", str(fixed), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    free = ROOT / "examples" / "diff_drive" / "problem.yaml"
    assert main(["solve", str(free), "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "*** FAILED ***" in captured.out and captured.err == ""
    assert "--quiet" in RECIPE.read_text() and "the report on stdout when the solve " \
        "succeeds" in " ".join(RECIPE.read_text().split())
