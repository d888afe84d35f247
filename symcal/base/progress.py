"""The progress seam: counted work shown as a bar on a terminal, and nothing elsewhere.

Library code that does counted work (units of a fleet, chunks of a pass over a huge log)
takes an optional :data:`Bars` factory and opens one :class:`Meter` per piece of work::

    with meter(bars, "fleet", total=len(units), unit="unit") as m:
        for ... in ...:
            m.advance()            # one more done
            m.note("failed=1")     # a short status beside the bar

``bars=None`` (the default everywhere) is silent and costs nothing.  The command line
passes :func:`terminal_bars`, which draws `tqdm <https://tqdm.github.io>`_ bars on
stderr only when stderr is a terminal, and passes None under ``--quiet``.  Lines that
must not be torn by a bar go through :func:`write_line`.  tqdm is imported only when a
bar is drawn.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from typing import Any, Protocol, TextIO


class Meter(Protocol):
    """One piece of counted work in progress."""

    def advance(self, n: int = 1) -> None:
        """Count ``n`` more steps done."""

    def note(self, text: str) -> None:
        """Show ``text`` (one short line) beside the count."""

    def close(self) -> None:
        """The work is over: remove the bar."""


#: A factory of meters: ``bars(label, total, unit)``; ``total`` None when unknown.
Bars = Callable[[str, int | None, str], Meter]


class NullMeter:
    """A meter that shows nothing (``bars=None``)."""

    def advance(self, n: int = 1) -> None:
        """Do nothing."""

    def note(self, text: str) -> None:
        """Do nothing."""

    def close(self) -> None:
        """Do nothing."""


#: Bars currently drawn by :func:`terminal_bars` (lines are then written through tqdm).
_OPEN: list[Any] = []


class _TqdmMeter:
    """A tqdm bar on ``stream``."""

    def __init__(self, label: str, total: int | None, unit: str, stream: TextIO) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc=label, unit=unit, file=stream, leave=False,
                        dynamic_ncols=True, mininterval=0.2)
        _OPEN.append(self.bar)

    def advance(self, n: int = 1) -> None:
        self.bar.update(n)

    def note(self, text: str) -> None:
        self.bar.set_postfix_str(text, refresh=False)

    def close(self) -> None:
        if self.bar in _OPEN:
            _OPEN.remove(self.bar)
        self.bar.close()


def is_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` is an interactive terminal."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def terminal_bars(stream: TextIO | None = None) -> Bars | None:
    """tqdm bars on ``stream`` (default: stderr) if it is a terminal, else None.

    Parameters
    ----------
    stream
        Where the bars are drawn; checked with ``isatty()`` when this is called.

    Returns
    -------
    Bars or None
        A factory of bars, or None (no bars: a file, a pipe, a test's capture).
    """
    out = sys.stderr if stream is None else stream
    if not is_terminal(out):
        return None

    def bars(label: str, total: int | None, unit: str) -> Meter:
        return _TqdmMeter(label, total, unit, out)

    return bars


@contextlib.contextmanager
def meter(bars: Bars | None, label: str, total: int | None = None,
          unit: str = "it") -> Iterator[Meter]:
    """A meter from ``bars`` (a silent one for None), closed when the block ends.

    Parameters
    ----------
    bars
        The factory (:func:`terminal_bars`), or None for no progress display.
    label
        What is counted, shown before the bar (``"fleet"``, ``"pass"``).
    total
        How many steps there will be (None: unknown, a count without a bar).
    unit
        The name of one step (``"unit"``, ``"chunk"``).
    """
    m: Meter = NullMeter() if bars is None else bars(label, total, unit)
    try:
        yield m
    finally:
        m.close()


def write_line(line: str, stream: TextIO | None = None) -> None:
    """Write one line on ``stream`` (default: stderr) without tearing an open bar."""
    out = sys.stderr if stream is None else stream
    if _OPEN:
        from tqdm import tqdm

        tqdm.write(line, file=out)
        return
    print(line, file=out, flush=True)
