"""Error types shared by every layer of symcal.

Every error a user can cause derives from :class:`SymcalError`; the CLI prints its
message (no traceback unless ``--debug``) and exits with its ``exit_code``:
2 for bad input, 1 for a failed solve.
"""

from __future__ import annotations

from dataclasses import dataclass

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1
#: Exit codes of a run stopped by SIGINT (Ctrl-C) and SIGTERM: 128 + the signal number.
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
#: Longest excerpt of a file's content an error message quotes.
EXCERPT_CHARS = 40


def escape_controls(text: str, keep: str = "") -> str:
    """``text`` with every control character written as an escape (``\\x1b``, ``\\n``).

    Parameters
    ----------
    text
        Any text, e.g. a name read from a file.
    keep
        Control characters to leave as they are (``"\\n\\t"`` for multi-line text).

    Returns
    -------
    str
        Text that cannot move a terminal's cursor, change its colours or ring its bell.
    """
    out = []
    for ch in text:
        if ch in keep or ch.isprintable() or ch == " ":
            out.append(ch)
        else:
            out.append(repr(ch)[1:-1] if ord(ch) < 0x10000 else f"\\U{ord(ch):08x}")
    return "".join(out)


def excerpt(text: object, limit: int = EXCERPT_CHARS) -> str:
    """A short, escaped excerpt of content read from a file, for an error message.

    Parameters
    ----------
    text
        The content (converted with ``str``).
    limit
        How many characters of it to show at most; longer text ends with ``...``.

    Returns
    -------
    str
        At most ``limit`` characters of ``text``, control characters escaped.
    """
    text = str(text)
    short = text if len(text) <= limit else text[:limit] + "..."
    return escape_controls(short)


class SymcalError(Exception):
    """Base class of every error symcal reports to a user.

    Parameters
    ----------
    message
        Text a person can act on; it names the offending file, key, symbol or column.
    """

    exit_code: int = EXIT_BAD_INPUT

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class Where:
    """Provenance of a value in a YAML file: file, 1-based line and key path.

    ``via`` names the file that was loaded when the value came from a file it
    ``extends`` (directly or not); :class:`SpecError` then says so after the message.
    """

    file: str
    line: int | None = None
    keypath: str = ""
    via: str | None = None

    def __str__(self) -> str:
        loc = self.file if self.line is None else f"{self.file}:{self.line}"
        return f"{loc}: {self.keypath}" if self.keypath else loc

    @property
    def note(self) -> str:
        """`` (in the base of FILE)`` for a value reached through an overlay, else ``""``."""
        return f" (in the base of {self.via})" if self.via else ""

    def child(self, key: str | int, line: int | None = None, file: str | None = None) -> Where:
        """Provenance of a child key (``parent.key``) at ``line`` (default: this line).

        ``file`` is the file that wrote the key when it differs from this one (a key
        merged from a base file); ``via`` then names the file that was loaded.
        """
        path = f"{self.keypath}.{key}" if self.keypath else str(key)
        line = self.line if line is None else line
        if file is None or file == self.file:
            return Where(self.file, line, path, self.via)
        top = self.via or self.file
        return Where(file, line, path, None if file == top else top)


class SpecError(SymcalError):
    """A YAML model, problem or scenario that cannot be used as written."""

    def __init__(self, where: Where, message: str) -> None:
        super().__init__(f"{where}: {message}{where.note}")
        self.where = where
        self.detail = message


class DataError(SymcalError):
    """A dataset that does not satisfy the data contract."""


class SolveError(SymcalError):
    """A solve that could not produce a usable estimate."""

    exit_code = EXIT_FAILED
