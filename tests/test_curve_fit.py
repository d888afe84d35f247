"""Curve fits without ceremony (issue 14): a problem with parameters, expressions and
constraints on data columns, and no sensor instance, is valid and solves to what scipy
finds; an unknown symbol that is a column of the data says so."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize

import symcal
from symcal.base.errors import SpecError

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
def folder(tmp_path: Path) -> Path:
    rng = np.random.default_rng(7)
    x = np.linspace(0, 5, 40)
    y = 2.5 * np.exp(-0.7 * x) + 0.01 * rng.normal(size=40)
    rows = [f"{float(a)!r},{float(b)!r}" for a, b in zip(x, y, strict=True)]
    (tmp_path / "d.csv").write_text("x,y\n" + "\n".join(rows) + "\n")
    return tmp_path


def test_a_curve_fit_needs_no_instance(folder: Path) -> None:
    (folder / "fit.yaml").write_text(FIT)
    result = symcal.solve(folder / "fit.yaml")
    assert result.success
    data = np.loadtxt(folder / "d.csv", delimiter=",", skiprows=1)
    popt, pcov = scipy.optimize.curve_fit(lambda x, a, k: a * np.exp(-k * x), data[:, 0],
                                          data[:, 1], p0=[1, 1])
    np.testing.assert_allclose([result.params[n].value for n in "ak"], popt, rtol=1e-7)
    se = [p.se for p in result.params.values()]
    np.testing.assert_allclose(se, np.sqrt(np.diag(pcov)), rtol=1e-5)


def test_an_unknown_symbol_that_is_a_data_column_points_to_it(folder: Path,
                                                              monkeypatch) -> None:
    monkeypatch.chdir(folder)
    (folder / "fit.yaml").write_text(FIT.replace("columns: {x: {unit: s}, y: {unit: mm}}",
                                                 "columns: {x: {unit: s}}"))
    with pytest.raises(SpecError) as err:
        symcal.load_problem("fit.yaml")
    assert str(err.value) == (
        "fit.yaml:7: constraints.r: unknown symbol 'y'; d.csv (dataset 'calibration') has a "
        "column 'y': declare it under 'columns:', e.g. columns: {y: {unit: mm}}")


def test_the_hint_never_reads_a_fifo(folder: Path, monkeypatch) -> None:
    monkeypatch.chdir(folder)
    os.mkfifo(folder / "pipe.csv")
    text = FIT.replace("columns: {x: {unit: s}, y: {unit: mm}}", "columns: {x: {}}")
    (folder / "fit.yaml").write_text(text.replace("d.csv", "pipe.csv"))
    with pytest.raises(SpecError, match=r"unknown symbol 'y'$"):
        symcal.load_problem("fit.yaml")


def test_a_problem_still_needs_constraints(folder: Path, monkeypatch) -> None:
    monkeypatch.chdir(folder)
    (folder / "fit.yaml").write_text(textwrap.dedent("""\
        problem: decay
        constraints: {}
        datasets: {calibration: {path: d.csv}}
        """))
    with pytest.raises(SpecError, match="fit.yaml:2: constraints: 'constraints' must not "
                                        "be empty"):
        symcal.load_problem("fit.yaml")
