"""The progress seam: lines of progress, and counted work shown as a bar on a terminal.

Every public function that works for a while takes the same two arguments, with the same
meaning (:func:`symcal.solve`, :func:`symcal.solve_partitioned`,
:func:`symcal.solve_fleet`, :func:`symcal.improve`, :func:`symcal.design`):

``progress``
    A :data:`Progress` callback, called with one line of text (no newline) per step of
    the work and per note about it: a solver's iterations, a fleet's units, an
    improvement's rounds.  None (the default): no lines.
``bars``
    A :data:`Bars` factory of meters (:func:`terminal_bars` draws them on a terminal),
    one meter per counted piece of work: a solve counts its solver iterations, a log kept
    as shards the shards each pass has done, a fleet its units, ``improve`` its rounds,
    ``design`` its optimisation rounds.  None (the default): no meters, at no cost.

With both, what a meter counts is shown on it and not written as a line: each counted
step advances the meter and its line (a solver's iteration line, a unit's outcome) is
shown beside the bar; every other line (a note, a gauge found before a solve, a round
of ``improve``) still goes to ``progress``.  Without ``bars`` every line goes to
``progress``.  The command line passes ``progress`` (lines on stderr) and
:func:`terminal_bars`, and neither under ``--quiet``.  Library code opens the seam with
:func:`reporting`; a :class:`Meter` is one bar::

    with reporting(progress, bars, "fleet", total=len(units), unit="unit") as report:
        for ... in ...:
            report.step("fleet: 3/10 unit A: solved")   # counted: a bar or a line
            report.line("a note")                       # always a line

Lines that must not be torn by a bar go through :func:`write_line`.  tqdm is imported
only when a bar is drawn.
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
    out.write(line + "\n")      # one write: an interrupt cannot fall between a line and
    out.flush()                 # its newline (the command's message then joined it)


#: Where the lines of progress go: called with one line of text (no newline); see the
#: module.
Progress = Callable[[str], None]


def is_step(line: str) -> bool:
    """Whether a solver's progress line is one of its counted steps (an iteration of
    ``lm`` or IPOPT: ``STAGE: iteration K ...``)."""
    return " iteration " in line


class Report:
    """The progress of one piece of work, as ``progress`` and ``bars`` ask for it (see
    the module).  Callable as a :data:`Progress` for code that reports lines only (the
    solvers): their counted steps (:func:`is_step`) go to the meter, the rest are lines.

    Attributes
    ----------
    meter
        The work's meter (a :class:`NullMeter` without bars).
    progress
        Where the lines go (None: nowhere).
    counts
        Whether a step advances the meter (False where the meter counts something else,
        the shards of a log, and the steps are only shown beside it).
    """

    def __init__(self, progress: Progress | None, m: Meter | None, counts: bool = True
                 ) -> None:
        self.progress = progress
        self.bar = m
        self.meter: Meter = m if m is not None else NullMeter()
        self.counts = counts

    @property
    def silent(self) -> bool:
        """Whether nothing is shown (no lines and no bar): callers may skip formatting."""
        return self.progress is None and self.bar is None

    def line(self, text: str) -> None:
        """A line of progress: written to ``progress``."""
        if self.progress is not None:
            self.progress(text)

    def step(self, text: str, n: int = 1) -> None:
        """A counted step: with a bar, the meter advances and shows ``text`` beside it;
        without one, ``text`` is a line."""
        if self.bar is None:
            self.line(text)
            return
        if self.counts:
            self.bar.advance(n)
        self.bar.note(text.strip())

    def __call__(self, text: str) -> None:
        """A solver's line: a step if :func:`is_step`, else a line."""
        if is_step(text):
            self.step(text)
        else:
            self.line(text)

    def callback(self) -> Progress | None:
        """This report as a solver's callback, None when it shows nothing."""
        return None if self.silent else self


@contextlib.contextmanager
def reporting(progress: Progress | None, bars: Bars | None, label: str,
              total: int | None = None, unit: str = "it", counts: bool = True
              ) -> Iterator[Report]:
    """The progress of one piece of work (see the module), its meter closed when the
    block ends.

    Parameters
    ----------
    progress
        Where the lines go (None: nowhere).
    bars
        The factory of meters (None: no meter).
    label, total, unit
        The meter's label, its total (None: unknown) and the name of one step.
    counts
        Whether a step advances the meter (see :class:`Report`).
    """
    if bars is None:
        yield Report(progress, None, counts)
        return
    with meter(bars, label, total, unit) as m:
        yield Report(progress, m, counts)
