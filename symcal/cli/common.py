"""What every command of the command line shares: the parser class, data options, progress,
the inputs and outputs of a command, and how any failure becomes one message and an exit
code."""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import signal
import stat
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from symcal.base import stops
from symcal.base.errors import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    SpecError,
    SymcalError,
    escape_controls,
    excerpt,
)

if TYPE_CHECKING:
    from symcal.base.progress import Bars
    from symcal.problem.symbolic import Problem


class UsageError(SymcalError):
    """A command line that argparse cannot parse, with the usage of the parser that failed."""

    def __init__(self, message: str, usage: str) -> None:
        super().__init__(message)
        self.usage = usage


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that a solve stops the same way (see solvers/nlp.py)."""


class Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors become :class:`UsageError` (exit 2)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message, self.format_usage())


def _data_option(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH, found '{text}'")
    return name, path


def debug_option(parser: argparse.ArgumentParser) -> None:
    """``--debug`` after the command name as well as before it."""
    parser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help=argparse.SUPPRESS)


def data_options(parser: argparse.ArgumentParser) -> None:
    """The options every command that reads a problem's data shares."""
    parser.add_argument("--data", action="append", type=_data_option, default=[],
                        metavar="NAME=PATH",
                        help="replace dataset NAME with a CSV, NPZ or Parquet file (for "
                             "'solve', the fitted dataset may be a folder of shards: a log "
                             "too large for memory)")
    parser.add_argument("--drop-invalid", action="store_true",
                        help="drop rows with NaN/inf instead of refusing the data")
    debug_option(parser)


def data_map(args: argparse.Namespace) -> dict[str, str]:
    """``--data NAME=PATH`` options as a mapping; a name given twice is an error."""
    out: dict[str, str] = {}
    for name, path in args.data:
        if name in out:
            raise SymcalError(f"--data {name}=... given twice")
        out[name] = path
    return out


def progress(line: str) -> None:
    """Print one progress line on stderr (above an open progress bar, never through it)."""
    from symcal.base.progress import write_line

    write_line(escape_controls(line), sys.stderr)


def progress_bars(args: argparse.Namespace) -> Bars | None:
    """The progress bars of a command (:mod:`symcal.base.progress`): tqdm bars on stderr when
    stderr is a terminal, None under ``--quiet`` or when stderr is a file or a pipe."""
    if getattr(args, "quiet", False):
        return None
    from symcal.base.progress import terminal_bars

    return terminal_bars(sys.stderr)


def progress_of(args: argparse.Namespace) -> tuple[Callable[[str], None] | None,
                                                   Bars | None]:
    """A command's ``progress`` and ``bars`` (:mod:`symcal.base.progress`): lines on
    stderr and, on a terminal, bars; neither under ``--quiet``."""
    if getattr(args, "quiet", False):
        return None, None
    return progress, progress_bars(args)


def out_lock(folder: str | Path | None, option: str) -> contextlib.AbstractContextManager:
    """The lock of the output folder ``folder`` for the rest of a command (nothing when
    None): a second command writing there is refused (:func:`symcal.base.files.writing_to`)."""
    if not folder:
        return contextlib.nullcontext()
    from symcal.base.files import writing_to

    return writing_to(folder, option)


def write_stdout(text: str) -> None:
    """Write a report to stdout, control characters (other than newline and tab) escaped."""
    sys.stdout.write(escape_controls(text, keep="\n\t"))


def inputs_of(args: argparse.Namespace, problems: Iterable[Problem] = ()) -> set[Path]:
    """The files a command reads that its outputs must never replace.

    Parameters
    ----------
    args
        The parsed command line: its problem files, ``--data`` files, ``--result`` and
        scenario.
    problems
        The loaded problems: every file each was built from (the files it extends, its
        models through their ``extends``), its data files, and the scenario files of its
        simulated datasets with the files they extend.
    """
    from symcal.language.overlay import extends_chain

    paths = {Path(args.problem).resolve()} if getattr(args, "problem", None) else set()
    paths |= {Path(p).resolve() for p in getattr(args, "problems", []) or []}
    paths |= {Path(p).resolve() for _, p in getattr(args, "data", [])}
    for key in ("result", "scenario"):
        if getattr(args, key, None):
            paths.add(Path(getattr(args, key)).resolve())
    if getattr(args, "scenario", None) and Path(args.scenario).is_file():
        paths |= set(extends_chain(args.scenario, "scenario"))
    for problem in problems:
        paths |= {Path(f).resolve() for f in problem.source_files()}
        for spec in problem.datasets.values():
            if spec.path is not None:
                paths.add(Path(spec.path).resolve())
            if spec.scenario is not None and spec.scenario.is_file():
                paths |= set(extends_chain(spec.scenario, "scenario"))
    return paths


# ----------------------------------------------------------------------- failures

def wants_json(argv: Sequence[str]) -> bool:
    """Whether the command line asks for JSON on stdout (``--json``)."""
    return "--json" in argv


@contextlib.contextmanager
def signals_handled() -> Iterator[None]:
    """Make SIGTERM raise :class:`Terminated`, and Ctrl-C (SIGINT, where Python's own
    handler has it) ``KeyboardInterrupt``, while the command runs (main thread only).

    Each also records the stop (:mod:`symcal.base.stops`), so that a stop some library
    swallowed is raised again at the next pass over the data or before an output set
    moves in; the record ends with the block.  A process forked meanwhile (the embedded
    cluster's workers on Linux) ends on SIGTERM as a fresh process does, and ignores
    Ctrl-C, which a terminal sends to every process of the command: the command itself
    stops its cluster."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    owner = os.getpid()

    def terminate(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != owner:     # a forked child (a Dask worker): end as by default
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        stops.request(Terminated)
        raise Terminated()

    def interrupt(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != owner:     # a forked worker: the command stops its cluster
            signal.signal(signum, signal.SIG_IGN)
            return
        stops.request(KeyboardInterrupt)
        raise KeyboardInterrupt

    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, terminate)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        stops.clear()


def _interrupted(exc: KeyboardInterrupt) -> tuple[str, int]:
    from symcal.base.files import committed

    what = ("terminated by SIGTERM" if isinstance(exc, Terminated)
            else "interrupted by SIGINT (Ctrl-C)")
    code = EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
    done = committed()
    if not done:
        return f"{what}; no output was written or changed", code
    return (f"{what}; only these outputs were written, each whole: "
            f"{', '.join(str(p) for p in done)}", code)


def _root_only(shown: str) -> bool:
    """Whether the file a message names is root's and others may not read it."""
    try:
        st = os.stat(shown)
    except (OSError, ValueError):
        return False
    return stat.S_ISREG(st.st_mode) and st.st_uid == 0 and not st.st_mode & stat.S_IROTH


def _without_content(exc: SymcalError) -> str:
    """The message of ``exc``, its quotes of a root-only file's content left out.

    A message quotes content between single quotes (and a YAML key in its key path): for
    a file of root's that others may not read (``/etc/shadow``), everything from the
    first quote to the last, and the key path, are replaced.
    """
    message = str(exc)
    where = getattr(exc, "where", None)
    if isinstance(exc, SpecError) and where is not None:
        head = where.file if where.line is None else f"{where.file}:{where.line}"
        file, detail = where.file, exc.detail
    else:
        head, sep, detail = message.partition(": ")
        file = head.rsplit(":", 1)[0] if head.rsplit(":", 1)[-1].isdigit() else head
        if not sep:
            return message
    if not _root_only(file):
        return message
    if "'" in detail:
        first, last = detail.index("'"), detail.rindex("'")
        detail = detail[:first] + "'…'" + detail[last + 1:] if last > first else \
            detail[:first] + "…"
    return f"{head}: {detail} (the file's content is not quoted: it is root's and others " \
           "may not read it)"


def failure(exc: BaseException) -> tuple[str, int]:
    """The one message and the exit code for any exception a command raised."""
    from symcal.base.files import LINK_LOOP, display_path

    if isinstance(exc, SymcalError):
        return _without_content(exc), exc.exit_code
    if isinstance(exc, KeyboardInterrupt):
        return _interrupted(exc)
    if isinstance(exc, MemoryError):
        return ("out of memory: the input is too large for this machine", EXIT_BAD_INPUT)
    if isinstance(exc, RecursionError):
        return "the input is nested too deeply to be read", EXIT_BAD_INPUT
    if isinstance(exc, RuntimeError) and str(exc).startswith("Symlink loop from "):
        exc = OSError(errno.ELOOP, LINK_LOOP, str(exc)[len("Symlink loop from "):].strip("'"))
    if isinstance(exc, OSError) and exc.errno == errno.ELOOP and exc.filename:
        return f"{excerpt(display_path(exc.filename), 200)}: {LINK_LOOP}", EXIT_BAD_INPUT
    if isinstance(exc, OSError):
        where = f"{excerpt(exc.filename, 200)}: " if exc.filename else ""
        return (f"{where}{exc.strerror or exc.__class__.__name__}", EXIT_BAD_INPUT)
    if isinstance(exc, UnicodeError):
        return f"text that is not valid UTF-8 ({excerpt(exc, 120)})", EXIT_BAD_INPUT
    return (f"internal error ({exc.__class__.__name__}: {excerpt(exc, 200)}); please report "
            "it with the output of 'symcal --debug ...'", EXIT_FAILED)


def report_failure(exc: BaseException, as_json: bool) -> int:
    """Print the message of ``exc`` on stderr (and a JSON error document on stdout when
    ``as_json``); return the exit code."""
    from symcal.base.files import json_text

    message, code = failure(exc)
    if isinstance(exc, UsageError):
        sys.stderr.write(exc.usage)
    sys.stderr.write(f"symcal: error: {escape_controls(message)}\n")   # one write
    if as_json:
        sys.stdout.write(json_text({"error": {"message": message, "exit_code": code}}))
    return code


def run_guarded(command: Callable[[], int], argv: Sequence[str]) -> int:
    """Run ``command()`` with SIGTERM handled; turn any failure into one message and an
    exit code (0 success, 1 failed solve, 2 bad input, 130 SIGINT, 143 SIGTERM), with a
    traceback only under ``--debug``.  A usage error raises ``SystemExit(2)``, as
    argparse does."""
    from symcal.base.files import forget_committed

    forget_committed()
    try:
        with signals_handled():
            return command()
    except SystemExit:
        raise
    except UsageError as exc:  # argparse's convention: usage errors exit
        raise SystemExit(report_failure(exc, wants_json(argv))) from None
    except BaseException as exc:
        if "--debug" in argv:
            raise
        return report_failure(exc, wants_json(argv))
