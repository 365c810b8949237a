"""`sandro-merge`: join sessions recorded at different times into one map, with no initial alignment.

Sessions are sandro-slam results folders (their session/ subfolder) or inputs sandro-slam reads (bags, scan folders,
KITTI sequences), which are processed first (into OUT/sessions/). The merged frame is the first session's world
frame. Writes into OUT (a new or empty folder, all or nothing):
    transforms.yaml                 per session: T_merged_session (4x4) and the 6x6 covariance of its first
                                    keyframe's pose (gtsam order [rotation, translation], keyframe frame)
    map.ply                         the keyframe submaps at their merged poses, voxelised, coloured by session
    trajectories/<name>.tum/.kitti  every frame's pose in the merged frame
    graph.g2o                       the merged keyframe graph (keys: gtsam symbols 'a'+session index, key)
    trajectories.png                top view of the merged trajectories with the inter-session loops
    summary.json                    sessions, loops (with weights and free-space conflicts), timings
When a session cannot be joined it says why, exits with 1 and writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from pipelines.cli.entry import EXIT_REFUSED, CommandError, Parser, one_line, run_command

if TYPE_CHECKING:
    from sandro_slam import MergeResult, Session, SlamConfig


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-merge`."""
    parser = Parser(prog="sandro-merge", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "sessions",
        type=Path,
        nargs="+",
        metavar="SESSION",
        help="sandro-slam results folder, or an input sandro-slam reads (at least two)",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder (new or empty)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (its merge section; default: built-in values)")
    parser.add_argument("--topic", help="point cloud topic (PointCloud2 or Livox CustomMsg) of bags given as sessions")
    parser.add_argument("--odometry", metavar="TOPIC", help="a topic of poses (nav_msgs/Odometry, ...) of the bags "
                        "given as sessions: their front end's odometry instead of KISS-ICP's")  # fmt: skip
    parser.add_argument("--workers", type=int, default=1, help="submap descriptions and pair registrations at once "
                        "on a local Ray (default 1: in this process; more needs pip install '.[cluster]')")  # fmt: skip
    parser.add_argument("--ray", metavar="ADDRESS", help="run them on an existing Ray cluster ('auto': the one this "
                        "machine belongs to)")  # fmt: skip
    parser.add_argument("--threads-per-task", type=int, default=0, metavar="N", help="threads each description or "
                        "registration may use (default 0: all)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit code 0 merged, 1 refused (sessions do not join), 2 bad input, 130 aborted."""
    return run_command(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    if len(args.sessions) < 2:
        raise CommandError("at least two sessions are needed")
    from pipelines.io.inputs import names_bag_poses

    if args.odometry is not None and not names_bag_poses(args.odometry):
        raise CommandError(f"--odometry {args.odometry}: not a topic name nor tf:FRAME (poses of the bags)")
    if args.workers < 1 or args.threads_per_task < 0:
        raise CommandError("--workers must be at least 1 and --threads-per-task at least 0")
    parallel = args.workers > 1 or args.ray is not None
    from pipelines.cluster import INSTALL_RAY, ray_available

    if parallel and not ray_available():
        raise CommandError(INSTALL_RAY)
    if args.out.exists() and (not args.out.is_dir() or any(args.out.iterdir())):
        raise CommandError(f"{args.out} exists and is not an empty folder: refusing to overwrite it")
    from pipelines.cluster import ray_map, ray_session, threads_limited
    from pipelines.io.atomic import atomic_dir
    from pipelines.io.merge_results import write_merge
    from sandro_slam import SlamConfig, merge_sessions
    from sandro_slam.merge.pipeline import merge_config, serial_map

    config = SlamConfig.load(args.config)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    threads = args.threads_per_task
    with atomic_dir(args.out) as out, threads_limited(threads):
        out.mkdir()
        with ray_session(args.workers, args.ray, threads, warm_up=True) if parallel else nullcontext():
            sessions = [
                _load_session(path, out / "sessions", config, args.topic, args.odometry) for path in args.sessions
            ]
            _unique_names(sessions)
            config = merge_config(config, sessions)
            result = merge_sessions(sessions, config, partial(ray_map, threads=threads) if parallel else serial_map)
        if not result.ok:
            refused = "; ".join(f"{name}: {why}" for name, why in result.refused.items())
            raise CommandError(f"refused, nothing written: {refused}", EXIT_REFUSED)
        write_merge(out, sessions, result, config)
    print_summary(args.out, result)
    return 0


def _is_input(path: Path) -> bool:
    """Whether `path` is something sandro-slam reads (a bag, a KITTI sequence, a folder of scans) rather than a
    results folder."""
    from pipelines.io.inputs import BAG_SUFFIXES
    from pipelines.io.scan_folder import SCAN_SUFFIXES

    if path.is_file():
        return path.suffix in BAG_SUFFIXES
    if not path.is_dir() or (path / "session").is_dir():
        return False
    return (
        (path / "metadata.yaml").is_file()
        or (path / "velodyne").is_dir()
        or any(p.suffix.lower() in SCAN_SUFFIXES for p in path.iterdir())
    )


def _load_session(
    path: Path, bag_out: Path, config: SlamConfig, topic: str | None, odometry: str | None = None
) -> Session:
    """A results folder's session, or an input's after running sandro-slam on it into `bag_out` (a bag on the
    poses of its topic `odometry`, when given)."""
    from pipelines.io.session import read_session

    if _is_input(path):
        from pipelines.io.inputs import detect_format, read_poses
        from pipelines.slam_run import run_input

        print(f"sandro-merge: processing {path} ...", flush=True)
        try:
            from_bag = odometry is not None and detect_format(path) == "bag"
            poses = read_poses(odometry, path, topic=topic) if from_bag else None
            folder, _ = run_input(path, bag_out, config, topic=topic, odometry=poses)
        except Exception as error:  # the bag reader's own errors: one line, like the other bad inputs
            raise ValueError(f"{path}: {one_line(error)}") from None
        return read_session(folder)
    return read_session(path)


def _unique_names(sessions: list[Session]) -> None:
    seen: dict[str, int] = {}
    for session in sessions:
        count = seen.get(session.name, 0)
        seen[session.name] = count + 1
        if count:
            session.name = f"{session.name}-{count}"


def print_summary(out: Path, result: MergeResult) -> None:
    """A few lines on stdout: each session's transform and the loops that joined it."""
    import numpy as np

    from pipelines.io.merge_results import merge_summary

    info = merge_summary(result)
    print(
        f"sandro-merge: {len(result.joined)} sessions joined in {result.timings['total']:.1f} s "
        f"({info['inter_session_loops_accepted']} inter-session loops kept of {info['inter_session_loops_verified']}"
        " verified)"
    )
    for name in result.joined:
        T = result.T_merged_session[name]
        yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
        sigma = np.sqrt(np.diag(result.covariance[name])[3:])
        print(
            f"  {name}: t = [{T[0, 3]:.2f}, {T[1, 3]:.2f}, {T[2, 3]:.2f}] m, yaw {yaw:.1f} deg, "
            f"sigma_t {np.linalg.norm(sigma):.3f} m"
        )
    print(f"results in {out}")


if __name__ == "__main__":
    sys.exit(main())
