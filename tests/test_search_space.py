"""A state column an instance reads is searched once (a new user's flow loop listed
``us: T, u_us, us.T, us.u, t, T``)."""

from __future__ import annotations

from test_gauge_dismissed import MODELS

import symcal
from symcal.revise.library import spaces


def test_a_state_column_an_instance_reads_is_listed_once(tmp_path) -> None:
    for name, text in MODELS.items():
        (tmp_path / name).write_text(text)
    found = spaces(symcal.load_problem(tmp_path / "problem.yaml"))
    assert found["us"].variables == ("T", "u_us", "us.T", "us.u", "t")
    assert found["cor"].variables == ("cor.m", "m_c", "t", "T")
    assert found["us"].describe() == ("us: T, u_us, us.T, us.u, t (every kind; default: its "
                                      "own readings, time and state columns)")
