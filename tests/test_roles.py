"""Dataset roles (issue 21 item 6): a problem is fitted on the dataset with ``role: fit``
(by default the one named ``calibration``) and every other dataset is held out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import symcal
from symcal.base.errors import SpecError

FIT = """\
problem: line
columns: {x: {unit: s}, y: {unit: mm}}
parameters:
  a: {value: 0, scale: 1}
  b: {value: 0, scale: 1}
constraints:
  r: y - (a + b*x)
datasets:
  first_run: {path: one.csv, role: check}
  bench: {path: two.csv, role: fit}
"""


def _write(path: Path, a: float, b: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, 30)
    y = a + b * x + 0.01 * rng.normal(size=x.size)
    rows = [f"{float(u)!r},{float(v)!r}" for u, v in zip(x, y, strict=True)]
    path.write_text("x,y\n" + "\n".join(rows) + "\n")
    return np.column_stack([x, y])


def test_the_fit_dataset_is_fitted_and_the_rest_held_out(tmp_path: Path) -> None:
    _write(tmp_path / "one.csv", 5.0, -1.0, 1)       # another line: held out, never fitted
    two = _write(tmp_path / "two.csv", 1.0, 2.0, 2)
    (tmp_path / "p.yaml").write_text(FIT)
    result = symcal.solve(tmp_path / "p.yaml")
    assert result.problem.fit_dataset == "bench"
    b, a = np.polyfit(two[:, 0], two[:, 1], 1)       # numpy's fit of the fitted data alone
    assert result.params["a"].value == pytest.approx(a, abs=1e-9)
    assert result.params["b"].value == pytest.approx(b, abs=1e-9)
    assert result.stat("r").dataset == "bench"        # the default dataset is the fitted one
    held = result.stat("r", "first_run").after.std
    assert held > 10 * result.stat("r").after.std     # the other line does not fit


def test_calibration_is_the_default_fit_unless_another_is_declared(tmp_path: Path) -> None:
    _write(tmp_path / "one.csv", 5.0, -1.0, 1)
    _write(tmp_path / "two.csv", 1.0, 2.0, 2)
    text = FIT.replace("first_run: {path: one.csv, role: check}", "calibration: {path: one.csv}")
    (tmp_path / "p.yaml").write_text(text)
    assert symcal.load_problem(tmp_path / "p.yaml").fit_dataset == "bench"
    (tmp_path / "q.yaml").write_text(text.replace(", role: fit}", "}"))
    assert symcal.load_problem(tmp_path / "q.yaml").fit_dataset == "calibration"


def test_two_fit_datasets_are_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.yaml").write_text(FIT.replace("role: check", "role: fit"))
    with pytest.raises(SpecError) as err:
        symcal.load_problem("p.yaml")
    assert str(err.value) == ("p.yaml:10: datasets.bench: datasets 'first_run' and 'bench' "
                              "both have role 'fit'; a problem is fitted on one dataset (give "
                              "the others 'role: check')")
