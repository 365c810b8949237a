"""`sandro-demo`: the main job on built-in data: simulate a LiDAR bag (once, then cached), run sandro-slam on it.

The bag is `sandro-simulate`'s drive (a 32-beam spinning LiDAR through a city of repeated, mirror-symmetric blocks,
with ground truth), cut to --frames scans: more than one lap, so the second lap closes loops on the first.
Prints where the results and the plot are, and the ATE before and after loop closure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.entry import Parser, run_command
from pipelines.cli.slam import print_summary

DEFAULT_CACHE = Path("results") / "demo-data"
DEFAULT_OUT = Path("results") / "demo"


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-demo`."""
    parser = Parser(prog="sandro-demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=500, help="scans in the simulated bag (default 500, ~1.2 laps)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated city and drive (default 0)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"where the bag is kept ({DEFAULT_CACHE})")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"base results folder ({DEFAULT_OUT})")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit codes as sandro-slam's."""
    return run_command(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    from pipelines.io.trajectory import read_trajectory
    from pipelines.simulation import VERSION
    from pipelines.simulation.export import ground_truth_path, simulate
    from pipelines.slam_run import run_input
    from sandro_slam import SlamConfig

    bag = args.cache / f"city_v{VERSION}_seed{args.seed}_{args.frames}scans.bag"
    config = SlamConfig.load(args.config)
    if not (bag.is_file() and ground_truth_path(bag).is_file()):
        print(f"simulating the demo bag {bag} (once) ...", flush=True)
        args.cache.mkdir(parents=True, exist_ok=True)
        simulate(bag, "ros1", seed=args.seed, frames=args.frames, overwrite=True, progress=True)
    print(f"sandro-slam {bag} --gt {ground_truth_path(bag)} --out {args.out}", flush=True)
    folder, metrics = run_input(
        bag, args.out, config, ground_truth=read_trajectory(ground_truth_path(bag)), progress=True
    )
    print_summary(folder, metrics)
    return 0


if __name__ == "__main__":
    sys.exit(main())
