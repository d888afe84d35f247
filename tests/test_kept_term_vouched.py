"""A term an earlier round kept, tested again by the final diagnosis, is not something
the floor "cannot vouch for": a new user's turntable (a gyro whose scale factor follows
the temperature, an optical and a magnetic encoder; `tests/data/turntable`) ended quiet
and at its floor with the right term, and the verdict still said `imu.bias (up to 107
SE), imu.prod_gyro_T (up to 76 SE)`: the kept product, evaluated again at the adjusted
readings, was only nearly absorbed by its own coefficient."""

from __future__ import annotations

import shutil

import pytest
from conftest import ROOT

import symcal
from symcal.report.text import unvouched


@pytest.mark.slow
def test_the_kept_term_is_not_named_again(tmp_path) -> None:
    shutil.copytree(ROOT / "tests" / "data" / "turntable", tmp_path / "t")
    folder = tmp_path / "t"
    (folder / "p.yaml").write_text((folder / "problem.yaml").read_text().replace(
        "simulate: scenario.yaml", "simulate: scen_a.yaml"))
    result = symcal.improve(folder / "p.yaml", tmp_path / "out")
    assert result.quiet
    assert [r.added for r in result.rounds[1:]] == ["imu.rate += the product of gyro and T"]
    assert unvouched(result.last) == []
    again = [c.label for c in result.last.candidates if "gyro" in c.label and "T" in
             c.label and c.basis.kind == "product"]
    assert again and all(not c.unseen for c in result.last.candidates
                         if c.label in again)
