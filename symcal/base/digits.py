"""How many digits an estimate is shown with: enough to reach its standard error.

Six significant digits hide an estimate's precision when it is far larger than its
standard error: a reference pressure of 1008.0012 hPa known to 0.0046 hPa printed as
``1008 ± 0.0046``.  An estimate is shown down to its standard error's second significant
digit (never fewer than six significant digits)."""

from __future__ import annotations

import math

#: Never fewer significant digits than this.
LEAST = 6
#: Never more (a double's own precision).
MOST = 17


def digits(value: float, se: float | None) -> int:
    """The significant digits that show ``value`` down to ``se``'s second significant
    digit, at least :data:`LEAST`."""
    if se is None or not math.isfinite(se) or se <= 0 or not math.isfinite(value) \
            or value == 0:
        return LEAST
    needed = math.floor(math.log10(abs(value))) - math.floor(math.log10(se)) + 2
    return min(max(LEAST, needed), MOST)


def estimate_text(value: float, se: float | None) -> str:
    """``value`` with :func:`digits` significant digits (``1008.0012`` for 1008.00123 ±
    0.0046; ``0.979486`` for 0.9794861 ± 6e-05)."""
    return format(value, f".{digits(value, se)}g")
