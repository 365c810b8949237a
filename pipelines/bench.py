"""`sandro-bench`: benchmarks of the project, one subcommand each (now: registration)."""

from __future__ import annotations

import argparse
import sys

from pipelines import bench_merge, bench_posegraph, bench_registration, bench_slam
from pipelines.bench_common import UsageError
from pipelines.cli import Parser
from pipelines.slam import InputError


SUBCOMMANDS = {"registration": bench_registration, "slam": bench_slam, "posegraph": bench_posegraph,
               "merge": bench_merge}


def build_parser() -> argparse.ArgumentParser:
    """The `sandro-bench` parser, with one subparser per benchmark."""
    parser = Parser(prog="sandro-bench", description=__doc__)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="BENCHMARK")
    for name, module in SUBCOMMANDS.items():
        doc = module.__doc__ or ""
        subparser = subparsers.add_parser(
            name, help=doc.splitlines()[0], description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
        )
        module.add_arguments(subparser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `sandro-bench`; returns the exit code (2 for bad arguments or input files, argparse's
    own included: it reports them by raising SystemExit)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        return SUBCOMMANDS[args.command].run(args)
    except (UsageError, InputError) as error:
        print(f"sandro-bench {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
