"""The ``--target`` a verdict prints reads back as the value it says (a new user's
``--target ifm.kT=3.3e-091/K`` was refused: the unit ran into the number)."""

from __future__ import annotations

import re
import shlex

import pytest

from symcal.experiment.command import target_arg
from symcal.experiment.optimize import _TARGET


@pytest.mark.parametrize(("unit", "expected"), [
    ("mm", "l_y=0.31mm"),
    ("1/K", "'l_y=0.31 1/K'"),
    ("", "l_y=0.31"),
    ("µm", "l_y=0.31µm"),
    ("m / s", "l_y=0.31m/s"),
])
def test_a_printed_target_reads_back(unit: str, expected: str) -> None:
    printed = target_arg("l_y", 0.3141, unit)
    assert printed == expected
    (word,) = shlex.split(printed)
    match = _TARGET.match(word)
    assert match is not None and match.group(1) == "l_y"
    assert float(match.group(2)) == pytest.approx(0.31)
    assert re.sub(r"\s", "", match.group(3) or "") == unit.replace(" ", "")
