"""Command-line interface: a thin argparse layer over the public API.

One module per command (``symcal/cli/<command>.py``), each with ``add_parser(subparsers)``
and ``run(args) -> exit code``; :func:`main` dispatches.  Exit codes: 0 success, 1 failed
solve, 2 bad input.  Errors are printed as one message without a traceback unless
``--debug`` is given.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from symcal.cli import codegen, compare, design, diagnose, improve, simulate, solve
from symcal.cli.common import Parser, run_guarded

#: The commands, in the order ``symcal --help`` lists them.
COMMANDS = {"solve": solve, "diagnose": diagnose, "improve": improve, "compare": compare,
            "codegen": codegen, "simulate": simulate, "design": design}


def _parser() -> argparse.ArgumentParser:
    parser = Parser(prog="symcal", description="Autonomous calibration through sensor "
                                               "redundancy.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for module in COMMANDS.values():
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code.

    Every failure is one message on stderr (and, with ``--json``, the document
    ``{"error": {"message": ..., "exit_code": N}}`` on stdout): 1 for a failed solve, 2 for
    bad input (files that cannot be read or written included), 130 after Ctrl-C and 143
    after SIGTERM.  A traceback is shown only with ``--debug``.
    """
    words = list(sys.argv[1:] if argv is None else argv)

    def command() -> int:
        args = _parser().parse_args(words)
        return int(COMMANDS[args.command].run(args))

    return run_guarded(command, words)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
