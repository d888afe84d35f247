"""What every command of the command line shares: the parser class, data options, progress."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from symcal.errors import EXIT_BAD_INPUT, SymcalError


class Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors exit with symcal's bad-input code."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"symcal: error: {message}\n")


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
                        metavar="NAME=PATH", help="replace dataset NAME with a CSV/NPZ file")
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
    """Print one progress line on stderr."""
    print(line, file=sys.stderr, flush=True)


def inputs_of(args: argparse.Namespace) -> set[Path]:
    """The files a command reads that its outputs must never replace."""
    paths = {Path(args.problem).resolve()} if getattr(args, "problem", None) else set()
    paths |= {Path(p).resolve() for p in getattr(args, "problems", []) or []}
    paths |= {Path(p).resolve() for _, p in getattr(args, "data", [])}
    return paths
