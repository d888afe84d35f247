"""A group of terms linear in another channel's reading is a coupling, not a
disagreement in gain: a magnetometer's ``Bx += a term linear in mz`` beside
``Bz += a term linear in mx`` read "the Bx and Bz channels of mag disagree in gain
(each a term linear in its own reading)", because mz is one of mag's inputs."""

from __future__ import annotations

from conftest import ROOT

from symcal.analysis.discovery import Basis, Candidate
from symcal.problem.build import load_problem
from symcal.revise.diagnose import _group_words, _read_by_output

MAG = ROOT / "tests" / "data" / "magnetometer_tc"


def _linear(output: str, variable: str) -> Candidate:
    return Candidate(output, Basis("linear", variable, f"a term linear in {variable}",
                                   ("lin",), ("{v}",)))


def test_each_output_reads_its_own_channel() -> None:
    problem = load_problem(MAG / "problem_base.yaml")
    own = _read_by_output(problem)
    assert own["mag.Bx"] == ("mag.mx", "mx")
    assert own["mag.Bz"] == ("mag.mz", "mz")
    own["mag"] = ("mag.mx", "mag.my", "mag.mz", "mx", "my", "mz")
    cross = _linear("mag.Bx", "mz")
    cross.indistinguishable = [_linear("mag.Bz", "mx").label]
    assert "disagree in gain" not in _group_words(cross, own)
    gains = _linear("mag.Bx", "mx")
    gains.indistinguishable = [_linear("mag.Bz", "mz").label]
    assert "the Bx and Bz channels of mag disagree in gain" in _group_words(gains, own)
