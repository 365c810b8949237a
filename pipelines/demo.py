"""`sandro-demo`: the main job on built-in data: simulate a LiDAR bag (once, then cached), run sandro-slam on it.

The bag is `sandro-simulate`'s drive (a 32-beam spinning LiDAR through a city of repeated, mirror-symmetric blocks,
with ground truth), cut to --frames scans: more than one lap, so the second lap closes loops on the first.
Prints where the results and the plot are, and the ATE before and after loop closure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.bag_io import BagError
from pipelines.cli import Parser
from pipelines.simulate import ground_truth_path, simulate_bag
from pipelines.simulation import VERSION as SIMULATION_VERSION
from pipelines.slam import InputError, load_config, print_summary, run_bag
from pipelines.trajectory_io import read_trajectory

DEFAULT_CACHE = Path("results") / "demo-data"
DEFAULT_OUT = Path("results") / "demo"


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit codes as sandro-slam's."""
    parser = Parser(prog="sandro-demo", description=__doc__,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=500, help="scans in the simulated bag (default 500, ~1.2 laps)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated city and drive (default 0)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"where the bag is kept ({DEFAULT_CACHE})")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"base results folder ({DEFAULT_OUT})")
    args = parser.parse_args(argv)
    bag = args.cache / f"city_v{SIMULATION_VERSION}_seed{args.seed}_{args.frames}scans.bag"
    try:
        config = load_config(args.config)
        if not (bag.is_file() and ground_truth_path(bag).is_file()):
            print(f"simulating the demo bag {bag} (once) ...", flush=True)
            args.cache.mkdir(parents=True, exist_ok=True)
            simulate_bag(bag, "ros1", seed=args.seed, frames=args.frames, overwrite=True, progress=True)
        print(f"sandro-slam {bag} --gt {ground_truth_path(bag)} --out {args.out}", flush=True)
        folder, metrics = run_bag(bag, args.out, config, ground_truth=read_trajectory(ground_truth_path(bag)),
                                  progress=True)
    except (InputError, BagError, ValueError, OSError) as error:
        print(f"sandro-demo: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sandro-demo: aborted", file=sys.stderr)
        return 130
    print_summary(folder, metrics)
    return 0


if __name__ == "__main__":
    sys.exit(main())
