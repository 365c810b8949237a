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

Several inputs (or --workers, --ray, --resume) make a batch: each input gets its own OUT/<name>/<YYYYmmdd-HHMMSS>
(<name>: the input's file or folder name without suffix) and OUT/batch.csv, OUT/batch.json sum them up (status,
frames, loops, frames/s, ATE, the error of a failed input). A failed input does not stop the others. --gt and
--odometry are then patterns with {name}, e.g. --gt 'truth/{name}.tum'. Inputs run as Ray tasks (pip install
'.[cluster]'): on a local Ray with --workers CPUs, or on an existing cluster with --ray ADDRESS. Exit code 1 when
an input failed.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from pipelines.cli.entry import EXIT_ABORTED, EXIT_REFUSED, CommandError, Parser, run_command

DEFAULT_OUT = Path("results") / "sandro-slam"


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-slam`."""
    parser = Parser(prog="sandro-slam", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", metavar="INPUT", type=Path, nargs="+", help="a bag, a folder of scans, a KITTI "
                        "sequence folder or a keyframe dump; several make a batch")  # fmt: skip
    parser.add_argument("--format", help="the input's format: bag, folder, kitti or keyframes (default: told from "
                        "its layout)")  # fmt: skip
    parser.add_argument(
        "--topic", help="point cloud topic, PointCloud2 or Livox CustomMsg (needed when the bag has several)"
    )
    parser.add_argument("--rate", type=float, help="scans per second [Hz] of a scan folder without other times")
    parser.add_argument("--odometry", metavar="POSES", help="poses of your own front end instead of "
                        "KISS-ICP: TUM (by time), KITTI (one per scan) or a bag's topic of poses (nav_msgs/Odometry, "
                        "...); scans with per-point times deskewed along timed poses")  # fmt: skip
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"base results folder (default {DEFAULT_OUT})")
    parser.add_argument("--gt", help="ground truth: TUM (matched by time), KITTI (one pose per scan) or a bag's "
                        "topic of poses")  # fmt: skip
    parser.add_argument("--max-frames", type=int, help="process at most this many scans")
    parser.add_argument("--refine", action=argparse.BooleanOptionalAction, help="a second pass: every scan "
                        "deskewed again, registered onto the loop-corrected map (default: the config's, auto: where "
                        "the sensor sways, as walking or handheld)")  # fmt: skip
    parser.add_argument("--sweep-times", choices=["auto", "none", "clockwise", "counterclockwise"], help="clouds "
                        "without per-point times: raw sweeps of a spinning LiDAR turning this way seen from above get "
                        "times from the azimuth; none: taken as deskewed; auto: told from the first 300 scans "
                        "(default: the config's, auto)")  # fmt: skip
    parser.add_argument("--map-voxel", type=float, default=0.2, help="voxel size of map.ply [m] (default 0.2)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    batch = parser.add_argument_group("batch (several inputs)")
    batch.add_argument("--workers", type=int, help="inputs run at once on a local Ray (default: the number of cores "
                       "with Ray installed, else 1: in this process)")  # fmt: skip
    batch.add_argument("--ray", metavar="ADDRESS", help="run on an existing Ray cluster ('auto': the one this machine "
                       "belongs to)")  # fmt: skip
    batch.add_argument("--resume", action="store_true", help="skip inputs whose results are complete")
    batch.add_argument("--threads-per-task", type=int, default=0, metavar="N", help="threads each input may use "
                       "(default 0: all)")  # fmt: skip
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
    if args.workers is not None and args.workers < 1:
        raise CommandError("--workers must be at least 1")
    if args.threads_per_task < 0:
        raise CommandError("--threads-per-task must be 0 (all) or more")
    from sandro_slam import SlamConfig

    config = SlamConfig.load(args.config)
    if args.refine is not None:
        config.refine = args.refine
    if args.sweep_times is not None:
        config.sweep_times = args.sweep_times
    if len(args.input) > 1 or args.workers is not None or args.ray is not None or args.resume:
        return _run_batch(args, config)
    from pipelines.io.inputs import read_poses
    from pipelines.slam_run import run_input

    notes: list[str] = []
    ground_truth, odometry = (
        read_poses(value, args.input[0], args.format, args.topic, notes) if value is not None else None
        for value in (args.gt, args.odometry)
    )
    for note in notes:
        print(f"sandro-slam: {note}", file=sys.stderr, flush=True)
    folder, metrics = run_input(
        args.input[0],
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


def _run_batch(args: argparse.Namespace, config) -> int:
    from pipelines.batch import jobs_for, run_batch, write_summary
    from pipelines.cluster import INSTALL_RAY, ray_available

    workers = args.workers
    if workers is None:
        workers = min(os.cpu_count() or 1, len(args.input)) if ray_available() else 1
    if (workers > 1 or args.ray is not None) and not ray_available():
        raise CommandError(INSTALL_RAY)
    jobs = jobs_for(
        args.input, args.out, gt=args.gt, odometry=args.odometry, config=config, fmt=args.format, topic=args.topic,
        rate=args.rate, max_frames=args.max_frames, map_voxel=args.map_voxel, threads=args.threads_per_task,
    )  # fmt: skip
    rows = run_batch(jobs, workers, args.ray, args.resume, progress=not args.quiet,
                     on_row=lambda so_far: write_summary(args.out, so_far))  # fmt: skip
    write_summary(args.out, rows)  # with the inputs a Ctrl-C left cancelled
    for row in rows:
        detail = row.get("error") or row.get("results") or ""
        print(f"{row['status']:<9} {row['input']}  {detail}")
    failed = sum(row["status"] == "failed" for row in rows)
    print(f"{len(rows) - failed} of {len(rows)} inputs done or skipped; summary: {args.out / 'batch.csv'}")
    if any(row["status"] in ("stopped", "cancelled") for row in rows):
        return EXIT_ABORTED
    return EXIT_REFUSED if failed else 0


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
