"""`sandro-bench`: the project's benchmarks, one subcommand each; docs/benchmarks.md holds their results."""

from __future__ import annotations

import argparse
import ast
import importlib
import sys
from importlib.util import find_spec
from pathlib import Path

from pipelines.cli.entry import Parser, run_command

BENCHMARKS = {  # subcommand -> module with add_arguments(parser) and run(args) -> exit code
    "registration": "pipelines.bench.registration",
    "slam": "pipelines.bench.slam",
    "posegraph": "pipelines.bench.posegraph",
    "merge": "pipelines.bench.merge",
    "batch": "pipelines.bench.batch",
    "suite": "pipelines.bench.suite",
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The `sandro-bench` parser: a subparser per benchmark, with the options of the one named in `argv` only,
    so that only that benchmark's module (and what it imports) is loaded."""
    parser = Parser(prog="sandro-bench", description=__doc__)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="BENCHMARK")
    chosen = next((arg for arg in argv if not arg.startswith("-")), None)
    for name, module_name in BENCHMARKS.items():
        doc = _docstring(module_name)
        summary = doc.splitlines()[0].split("`: ", 1)[-1]  # without the leading "`sandro-bench NAME`: "
        subparser = subparsers.add_parser(
            name, help=summary, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
        )
        subparser.set_defaults(prog=subparser.prog)
        if name == chosen:
            importlib.import_module(module_name).add_arguments(subparser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `sandro-bench`; returns the exit code (2 for bad arguments or input files)."""
    argv = sys.argv[1:] if argv is None else argv
    return run_command(build_parser(argv), _run, argv)


def _run(args: argparse.Namespace) -> int:
    return importlib.import_module(BENCHMARKS[args.command]).run(args)


def _docstring(module_name: str) -> str:
    """A module's docstring, read from its source without importing it."""
    source = Path(find_spec(module_name).origin).read_text()
    return ast.get_docstring(ast.parse(source)) or ""


if __name__ == "__main__":
    sys.exit(main())
