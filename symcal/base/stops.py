"""A stop the user asked for (SIGTERM, Ctrl-C) that other code may have swallowed.

Python runs a signal's handler in the main thread at the next point where its
interpreter checks for one, and the exception the handler raises appears there, inside
whatever code runs at that moment.  Code that catches everything swallows it, and the
stop is lost: CasADi converts a numpy argument under a bare ``except:``, and in a loop of
small CasADi calls two signals in three vanished that way (measured).  So the command
line's handlers (:func:`symcal.cli.common.signals_handled`) record the stop here as well
as raising it, and symcal calls :func:`check` at the start of every pass over the data
and before an output set moves in: a swallowed stop is raised again there.  Nothing is
recorded outside the command line, and the record ends with the command.
"""

from __future__ import annotations

from symcal.base.forks import in_forked_child

_REQUESTED: list[type[KeyboardInterrupt]] = []


def request(kind: type[KeyboardInterrupt]) -> None:
    """Record that the user asked to stop (the first request is kept)."""
    if not _REQUESTED:
        _REQUESTED.append(kind)


def check() -> None:
    """Raise the recorded stop again, if there is one.

    Raises
    ------
    KeyboardInterrupt
        The recorded kind (the command line's SIGTERM is a subclass).
    """
    if _REQUESTED:
        raise _REQUESTED[0]()


def clear() -> None:
    """Forget the recorded stop (the command that recorded it has ended)."""
    _REQUESTED.clear()


in_forked_child(clear)
