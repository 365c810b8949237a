"""`sandro-slam`: offline SLAM post-processing of a ROS1/ROS2 bag or a folder of scans: odometry (KISS-ICP, or
the poses of your own front end), SANDRO loop closures, a robust gtsam pose graph; an optimised trajectory and map out.

Inputs (told apart by their layout, or --format): a ROS1 .bag, a ROS2 bag folder or .mcap/.db3 file (bag); a folder
of .bin/.pcd/.ply scans, one per file (folder); a KITTI odometry sequence folder with velodyne/ (kitti: its poses.txt
is the ground truth); a folder of deskewed scans with the poses that made them, poses.txt/.tum/.kitti beside them
(keyframes: those poses are the odometry). Scan times of folders come from a times.txt beside the scans, from the
file names when they are time stamps, or from --rate.

Each run writes a new folder OUT/<YYYYmmdd-HHMMSS> (OUT/latest points at it):
    poses.tum, poses.kitti          T_world_sensor per scan after loop closure (world = the first scan's frame;
                                    times = the scan's stamp + its latest per-point time, which KISS-ICP deskews to)
    odometry.tum, odometry.kitti    the same from the odometry alone (the poses given, with --odometry)
    graph.g2o                       the keyframe pose graph (odometry + loops), vertices at the optimised poses
    loops.csv                       every verified loop, its covariance diagonal, GNC weight and verdict
    map.ply                         the keyframe submaps at their optimised poses, voxelised
    trajectory.png                  top view before/after with accepted and rejected loops
    config.yaml, metrics.json       the configuration used; frames/s, loop counts, ATE/RPE against --gt
    session/                        keyframe submaps and graph, for sandro-merge
Ctrl-C stops reading and still optimises and writes everything; a second Ctrl-C aborts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.entry import CommandError, Parser, run_command

DEFAULT_OUT = Path("results") / "sandro-slam"


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-slam`."""
    parser = Parser(prog="sandro-slam", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", metavar="INPUT", type=Path, help="a bag, a folder of scans, a KITTI sequence folder "
                        "or a keyframe dump")  # fmt: skip
    parser.add_argument("--format", help="the input's format: bag, folder, kitti or keyframes (default: told from "
                        "its layout)")  # fmt: skip
    parser.add_argument("--topic", help="sensor_msgs/PointCloud2 topic (needed when the bag has several)")
    parser.add_argument("--rate", type=float, help="scans per second [Hz] of a scan folder without other times")
    parser.add_argument("--odometry", type=Path, metavar="POSES", help="poses of your own front end instead of "
                        "KISS-ICP: TUM (by time) or KITTI (one per scan); the scans deskewed already")  # fmt: skip
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"base results folder (default {DEFAULT_OUT})")
    parser.add_argument("--gt", type=Path, help="ground truth: TUM (matched by time) or KITTI (one pose per scan)")
    parser.add_argument("--max-frames", type=int, help="process at most this many scans")
    parser.add_argument("--map-voxel", type=float, default=0.2, help="voxel size of map.ply [m] (default 0.2)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit codes: 0 done, 2 bad input (an input without any usable scan included), 130 aborted."""
    return run_command(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    if args.max_frames is not None and args.max_frames < 1:
        raise CommandError("--max-frames must be at least 1")
    if args.map_voxel <= 0:
        raise CommandError("--map-voxel must be positive")
    if args.rate is not None and not args.rate > 0:
        raise CommandError("--rate must be positive")
    from pipelines.io.trajectory import read_trajectory
    from pipelines.slam_run import run_input
    from sandro_slam import SlamConfig

    config = SlamConfig.load(args.config)
    ground_truth = read_trajectory(args.gt) if args.gt is not None else None
    odometry = read_trajectory(args.odometry) if args.odometry is not None else None
    folder, metrics = run_input(
        args.input,
        args.out,
        config,
        fmt=args.format,
        topic=args.topic,
        rate=args.rate,
        ground_truth=ground_truth,
        odometry=odometry,
        max_frames=args.max_frames,
        map_voxel=args.map_voxel,
        progress=not args.quiet,
    )
    print_summary(folder, metrics)
    return 0


def print_summary(folder: Path, metrics: dict) -> None:
    """What a run did, its ATE against the ground truth when known, and where its results are."""
    stopped = " (stopped early by Ctrl-C)" if metrics["interrupted"] else ""
    print(
        f"{metrics['frames']} scans{stopped}, {metrics['frames_per_s']:.1f} frames/s, {metrics['keyframes']} "
        f"keyframes, {metrics['loops_accepted']} loops accepted, {metrics['loops_rejected']} rejected"
    )
    if "ground_truth" in metrics:
        gt = metrics["ground_truth"]
        print(
            f"ATE odometry {gt['ate_odometry_m']:.3f} m -> after loop closure {gt['ate_slam_m']:.3f} m "
            f"({gt['frames_matched']} scans matched to the ground truth)"
        )
    print(f"results: {folder}")
    print(f"plot:    {folder / 'trajectory.png'}")


if __name__ == "__main__":
    sys.exit(main())
