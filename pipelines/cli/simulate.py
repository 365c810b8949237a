"""`sandro-simulate`: write a simulated LiDAR drive as a ROS bag or as a folder of scans, with its ground truth.

The drive is `pipelines.simulation.simulate_sequence`: a 32-beam spinning LiDAR at 10 Hz through a seeded city
of repeated and mirror-symmetric blocks, raw (not deskewed) points with range noise. In a bag each message is a
sensor_msgs/PointCloud2 of x, y, z (float32) and t (uint32, ns after header.stamp, the Ouster convention) in the
sensor frame, or with --message livox a Livox CustomMsg (livox_ros_driver's in ROS1, livox_ros_driver2's in ROS2)
of the same points, offset_time in ns after timebase; header.stamp (and timebase) is the sweep start.
Folders (OUT a folder):
    folder      the same raw scans as PCD files (x, y, z and t), times.txt the sweep starts
    kitti       the KITTI odometry layout: velodyne/*.bin deskewed scans, times.txt, poses.txt the true poses
    keyframes   a LiDAR-inertial front end's keyframe dump: deskewed PCD scans, times.txt, and poses.txt its
                odometry, the true poses drifting by --drift % of the distance
The ground truth T_world_sensor goes beside OUT as OUT.gt.tum (TUM: t x y z qx qy qz qw), sampled at 100 Hz from
the first sweep's start to the last sweep's end, on the scans' clock.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from pipelines.cli.entry import CommandError, Parser, run_command
from pipelines.io.bags import MESSAGES, is_topic_name
from pipelines.simulation.export import BAG_FORMATS, DEFAULT_START_TIME, FOLDER_FORMATS, ground_truth_path, simulate


def _bounded(kind: Callable[[str], float], low: float, what: str) -> Callable[[str], float]:
    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not value >= low:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    """The `sandro-simulate` parser."""
    parser = Parser(prog="sandro-simulate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "out",
        metavar="OUT",
        type=Path,
        help="what to write: a .bag file (ros1), a folder (ros2-*, and the scan folders); ground truth in OUT.gt.tum",
    )
    parser.add_argument(
        "--format",
        choices=BAG_FORMATS + FOLDER_FORMATS,
        help="bag or scan folder format (default: ros1 when OUT ends in .bag, else ros2-mcap)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seeds the city, the wobble and the noise (default 0)")
    parser.add_argument(
        "--laps",
        type=_bounded(int, 1, "a whole number >= 1"),
        default=2,
        help="laps of the ~400 m loop (default 2, ~800 scans)",
    )
    parser.add_argument(
        "--frames", type=_bounded(int, 1, "a whole number >= 1"), help="at most this many scans (default: all laps)"
    )
    parser.add_argument(
        "--noise",
        type=_bounded(float, 0.0, "a number >= 0"),
        default=0.02,
        metavar="SIGMA",
        help="range noise standard deviation [m] (default 0.02)",
    )
    parser.add_argument("--topic", default="/points", help="topic of the scans (default /points)")
    parser.add_argument(
        "--message",
        choices=MESSAGES,
        default="pointcloud2",
        help="message type of a bag's scans: sensor_msgs/PointCloud2 or Livox CustomMsg (default pointcloud2)",
    )
    parser.add_argument(
        "--odometry-topic",
        metavar="TOPIC",
        help="write a LiDAR-inertial front end's output instead of raw scans: the scans deskewed (no per-point "
        "times) and its odometry (the true poses drifting by --drift) as nav_msgs/Odometry on TOPIC",
    )
    parser.add_argument(
        "--start-time",
        type=_bounded(float, 0.0, "a number >= 0"),
        default=DEFAULT_START_TIME,
        metavar="SECONDS",
        help=f"header.stamp of the first scan (default {DEFAULT_START_TIME:.0f})",
    )
    at_least_zero = _bounded(float, 0.0, "a number >= 0")
    parser.add_argument("--drift", type=at_least_zero, default=0.5, metavar="PERCENT",
                        help="drift of the odometry of a keyframe dump or of --odometry-topic in %% of the distance "
                        "(default 0.5)")  # fmt: skip
    parser.add_argument("--force", action="store_true", help="replace OUT and its ground truth if they exist")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `sandro-simulate`; exit codes: 0 written, 2 bad arguments or an unwritable OUT, 130 aborted."""
    return run_command(build_parser(), _run, argv, aborted="interrupted, nothing written")


def _run(args: argparse.Namespace) -> int:
    out: Path = args.out
    fmt = args.format or ("ros1" if out.suffix == ".bag" else "ros2-mcap")
    if (fmt == "ros1") != (out.suffix == ".bag"):
        raise CommandError(f"OUT must end in .bag for --format ros1, and not otherwise (got {out} for {fmt})")
    if args.message != "pointcloud2" and fmt not in BAG_FORMATS:
        raise CommandError(f"--message {args.message} is for bags, not for --format {fmt}")
    if args.odometry_topic is not None and fmt not in BAG_FORMATS:
        raise CommandError(f"--odometry-topic is for bags, not for --format {fmt}")
    if args.odometry_topic is not None and not is_topic_name(args.odometry_topic):
        raise CommandError(f"--odometry-topic {args.odometry_topic}: not a topic name")
    existing = [p for p in (out, ground_truth_path(out)) if p.exists() or p.is_symlink()]
    if existing and not args.force:
        raise CommandError(f"{existing[0]} exists (use --force to replace it)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        count = simulate(
            out,
            fmt,
            args.seed,
            args.laps,
            args.frames,
            args.noise,
            args.topic,
            args.start_time,
            drift=args.drift / 100.0,
            overwrite=args.force,
            progress=True,
            message=args.message,
            odometry_topic=args.odometry_topic,
        )
    except OSError as error:
        raise CommandError(f"cannot write {out}: {error.strerror or error}") from None
    where = f" on {args.topic}" if fmt in BAG_FORMATS else ""
    if args.odometry_topic is not None:
        where += f", deskewed, odometry on {args.odometry_topic}"
    print(f"wrote {out} ({fmt}, {count} scans{where}) and {ground_truth_path(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
