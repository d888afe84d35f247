"""Estimates are shown down to their standard error (a new user's altimeter: a reference
pressure known to 0.0046 hPa was printed as ``1008 ± 0.0046``)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from symcal.base.digits import LEAST, estimate_text


@pytest.mark.parametrize(("value", "se", "text"), [
    (1008.00123, 0.0046, "1008.0012"),
    (0.9794861, 6e-05, "0.979486"),
    (-1008.00123, 0.0046, "-1008.0012"),
    (122.67098, 0.016, "122.671"),
    (123456789.4, 10.0, "123456789"),
    (1008.00123, None, "1008"),
    (1008.00123, float("nan"), "1008"),
    (1008.00123, 0.0, "1008"),
    (3.0, 50.0, "3"),
    (0.0, 1e-3, "0"),
])
def test_an_estimate_reaches_its_standard_error(value: float, se: float | None,
                                                text: str) -> None:
    assert estimate_text(value, se) == text


@given(st.floats(min_value=-1e12, max_value=1e12, allow_nan=False).filter(lambda v: v != 0),
       st.floats(min_value=1e-12, max_value=1e12))
def test_the_text_is_within_a_tenth_of_the_standard_error(value: float, se: float) -> None:
    shown = float(estimate_text(value, se))
    assert abs(shown - value) <= max(0.05 * se, 5 * 10 ** -LEAST * abs(value)) * (1 + 1e-12)
