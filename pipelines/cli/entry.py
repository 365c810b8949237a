"""What every command-line tool shares: a parser whose errors are one line, one error type, the exit codes,
and the wrapper that turns errors into one line on stderr and an exit code instead of a traceback."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import NoReturn

EXIT_OK = 0
EXIT_REFUSED = 1  # the input was read but the job cannot be done (sandro-merge: sessions that do not join)
EXIT_BAD_INPUT = 2  # bad arguments or input files
EXIT_ABORTED = 130  # Ctrl-C


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


class CommandError(Exception):
    """What a command reports as one line and an exit code: bad input (exit 2, "error: ..."), or a job that cannot
    be done (exit 1, the message as it is)."""

    def __init__(self, message: str, exit_code: int = EXIT_BAD_INPUT):
        super().__init__(message)
        self.exit_code = exit_code


def one_line(error: BaseException) -> str:
    """An exception's message on one line (its type's name when it has none)."""
    return " ".join(str(error).split()) or type(error).__name__


def run_command(
    parser: argparse.ArgumentParser,
    command: Callable[[argparse.Namespace], int],
    argv: list[str] | None = None,
    aborted: str = "aborted",
) -> int:
    """Parse `argv` and run `command(args)`; returns the exit code.

    CommandError, ValueError (bad input files and values) and OSError (files that cannot be read or written)
    become one line on stderr naming the program (`args.prog` when the parser sets it, as a subcommand may), Ctrl-C
    the line `aborted` and exit code 130; argparse's own exits (--help, bad arguments) return their code.
    """
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    prog = getattr(args, "prog", parser.prog)
    try:
        return command(args)
    except CommandError as error:
        prefix = "error: " if error.exit_code == EXIT_BAD_INPUT else ""
        _report(f"{prog}: {prefix}{one_line(error)}")
        return error.exit_code
    except (ValueError, OSError) as error:
        _report(f"{prog}: error: {one_line(error)}")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        _report(f"{prog}: {aborted}")
        return EXIT_ABORTED


def _report(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
