"""How numbers are shown in the console and in RESULTS.md."""

from __future__ import annotations

import math


def show(a: float | None) -> str:
    """A fitted exponent, or a dash when there is none."""
    return "—" if a is None else f"{a:.2f}"


def fmt_time(t: float) -> str:
    """Seconds as ms below 1 s, else as s."""
    return f"{t * 1e3:.1f} ms" if t < 1 else f"{t:.2f} s"


def fmt_n(n: int) -> str:
    """An observation count, as 1eK when it is a power of ten."""
    e = int(round(math.log10(n)))
    return f"1e{e}" if 10**e == n else str(n)


def say(text: str) -> None:
    """One line of progress on stdout, flushed."""
    print(text, flush=True)
