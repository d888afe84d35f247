"""The whole product in ``symcal`` (issue 21 item 4): every public name resolves to the
object its module defines, whatever was imported before, and a Result and a Diagnosis
display their report in IPython and Jupyter."""

from __future__ import annotations

import html
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import symcal

FIT = """\
problem: decay
columns: {x: {unit: s}, y: {unit: mm}}
parameters:
  a: {value: 1, scale: 1}
  k: {value: 1, scale: 1}
constraints:
  r: y - a*exp(-k*x)
datasets:
  calibration: {path: d.csv}
"""


@pytest.fixture
def fitted(tmp_path: Path) -> symcal.Result:
    rng = np.random.default_rng(3)
    x = np.linspace(0, 5, 40)
    y = 2.0 * np.exp(-0.5 * x) + 0.01 * rng.normal(size=40)
    rows = [f"{float(a)!r},{float(b)!r}" for a, b in zip(x, y, strict=True)]
    (tmp_path / "d.csv").write_text("x,y\n" + "\n".join(rows) + "\n")
    (tmp_path / "fit.yaml").write_text(FIT)
    return symcal.solve(tmp_path / "fit.yaml")


def test_every_public_name_is_its_modules_object() -> None:
    for name in symcal.__all__:
        value = getattr(symcal, name)
        if name in symcal._LAZY:
            module, attr = symcal._LAZY[name]
            assert value is getattr(importlib.import_module(module), attr), name


def test_the_verbs_are_functions_not_folders() -> None:
    """``symcal.design``, ``codegen`` and ``simulate`` name functions: no folder of the
    package has those names, so importing its modules cannot shadow them."""
    import symcal.experiment.optimize
    import symcal.export.c
    import symcal.simulation  # noqa: F401

    for name in ("diagnose", "improve", "compare", "design", "codegen", "simulate",
                 "predict", "solve", "solve_fleet", "solve_partitioned"):
        assert callable(getattr(symcal, name)) and not isinstance(getattr(symcal, name),
                                                                 type(symcal)), name
    folders = {p.name for p in Path(symcal.__file__).parent.iterdir() if p.is_dir()}
    assert not folders & set(symcal.__all__)


def test_import_symcal_stays_light() -> None:
    code = ("import sys, symcal; heavy = [m for m in ('casadi', 'scipy', 'pint', 'dask') "
            "if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_a_result_and_a_diagnosis_display_their_report(fitted: symcal.Result) -> None:
    text = symcal.text_report(fitted)
    assert fitted._repr_html_() == f"<pre style=\"font-size: 90%\">{html.escape(text)}</pre>"

    class Printer:
        def __init__(self) -> None:
            self.out: list[str] = []

        def text(self, s: str) -> None:
            self.out.append(s)

    printer = Printer()
    fitted._repr_pretty_(printer, False)
    assert printer.out == [text]
    diagnosis = symcal.diagnose(fitted)
    assert html.escape(symcal.diagnosis_report(diagnosis)) in diagnosis._repr_html_()
