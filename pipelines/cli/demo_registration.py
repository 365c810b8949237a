"""`python -m pipelines.cli.demo_registration`: register the bundled real LiDAR pair (small_gicp) with no initial
guess.

FPFH correspondences, SANDRO, errors against the ground truth, and the aligned clouds written as a PLY.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.entry import Parser, run_command

DEFAULT_PAIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "small_gicp"


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of the registration demo."""
    parser = Parser(prog="python -m pipelines.cli.demo_registration", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--pair", type=Path, default=DEFAULT_PAIR, help="folder with source.ply, target.ply, T_target_source.txt"
    )
    parser.add_argument("--voxel", type=float, default=0.5, help="FPFH voxel size [m]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random move of the source")
    parser.add_argument("--out", type=Path, default=Path("results/demo_registration"), help="output folder")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit codes: 0 registered within 10 deg and 1 m of the truth, 1 not, 2 bad input."""
    return run_command(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    import numpy as np

    from pipelines.evaluation import pose_errors
    from pipelines.io.pointclouds import load_point_cloud, write_point_cloud
    from pipelines.io.trajectory import read_transform
    from pipelines.simulation.correspondences import random_transform
    from sandro_core import SandroConfig, register
    from sandro_core.features import match_fpfh
    from sandro_core.geometry import transform_points

    source = load_point_cloud(args.pair / "source.ply")
    target = load_point_cloud(args.pair / "target.ply")
    T_gt = read_transform(args.pair / "T_target_source.txt")

    # Move the source far away so that no initial guess can help.
    T_moved_source = random_transform(np.random.default_rng(args.seed), max_translation=10.0)
    moved = transform_points(T_moved_source, source)
    T_true = T_gt @ np.linalg.inv(T_moved_source)

    P, Q = match_fpfh(moved, target, args.voxel, source_viewpoint=T_moved_source[:3, 3])
    register(P, Q, SandroConfig(noise_bound=args.voxel))  # the first call loads the compiled kernels
    result = register(P, Q, SandroConfig(noise_bound=args.voxel))
    T = result.transformation
    rot_err, trans_err = pose_errors(T, T_true)
    print(f"{len(P)} FPFH correspondences, {len(result.inliers)} inliers, valid={result.valid}")
    print(f"solver time {result.time_s * 1e3:.1f} ms; error {rot_err:.2f} deg, {trans_err:.3f} m")
    print(
        "rotation / translation std [deg, m]:",
        np.round(np.degrees(np.sqrt(np.diag(result.covariance)[:3])), 3),
        np.round(np.sqrt(np.diag(result.covariance)[3:]), 3),
    )

    args.out.mkdir(parents=True, exist_ok=True)
    colors = np.zeros((len(target) + len(moved), 3))
    colors[: len(target)] = [0.1, 0.4, 0.9]
    colors[len(target) :] = [0.9, 0.3, 0.1]
    path = args.out / "aligned.ply"
    write_point_cloud(path, np.vstack([target, transform_points(T, moved)]), colors)
    print(f"aligned clouds (target blue, source orange): {path}")
    return 0 if result.valid and rot_err < 10 and trans_err < 1 else 1


if __name__ == "__main__":
    sys.exit(main())
