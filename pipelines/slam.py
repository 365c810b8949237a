"""`sandro-slam`: offline SLAM post-processing of a ROS1/ROS2 bag: KISS-ICP odometry, SANDRO loop closures,
a robust gtsam pose graph; an optimised trajectory and map out.

Each run writes a new folder OUT/<YYYYmmdd-HHMMSS> (OUT/latest points at it):
    poses.tum, poses.kitti          T_world_sensor per frame after loop closure (world = the first scan's frame;
                                    times = header.stamp + the latest per-point time, which KISS-ICP deskews to)
    odometry.tum, odometry.kitti    the same from KISS-ICP alone
    graph.g2o                       the keyframe pose graph (odometry + loops), vertices at the optimised poses
    loops.csv                       every verified loop, its covariance diagonal, GNC weight and verdict
    map.ply                         the keyframe submaps at their optimised poses, voxelised
    trajectory.png                  top view before/after with accepted and rejected loops
    config.yaml, metrics.json       the configuration used; frames/s, loop counts, ATE/RPE against --gt
    session/                        keyframe submaps and graph, for sandro-merge
Ctrl-C stops reading the bag and still optimises and writes everything; a second Ctrl-C aborts.
"""

from __future__ import annotations

import argparse
import itertools
import json
import signal
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from pipelines.atomic_write import atomic_path, write_text_atomic
from pipelines.bag_io import BagError, BagScans
from pipelines.cli import Parser
from pipelines.results_folder import link_latest, new_run_folder
from pipelines.session_io import write_session
from pipelines.slam_outputs import plot_trajectories, write_graph, write_loops, write_map, write_trajectories
from pipelines.trajectory_io import read_trajectory
from pipelines.trajectory_metrics import ate, interpolate_poses, rpe
from sandro_slam import OfflineSlam, SlamConfig, SlamResult

DEFAULT_OUT = Path("results") / "sandro-slam"
GT_MAX_GAP = 0.25  # [s] ground-truth samples farther apart than this are not interpolated between


class InputError(Exception):
    """Bad arguments or input files: one line on stderr, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-slam`."""
    parser = Parser(prog="sandro-slam", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", type=Path, help="ROS1 .bag file, ROS2 bag folder (sqlite3 or mcap) or .mcap file")
    parser.add_argument("--topic", help="sensor_msgs/PointCloud2 topic (needed when the bag has several)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"base results folder (default {DEFAULT_OUT})")
    parser.add_argument("--gt", type=Path, help="ground truth: TUM (matched by time) or KITTI (one pose per message)")
    parser.add_argument("--max-frames", type=int, help="process at most this many scans")
    parser.add_argument("--map-voxel", type=float, default=0.2, help="voxel size of map.ply [m] (default 0.2)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit codes: 0 done, 2 bad input (a bag without any usable scan included), 130 aborted."""
    args = build_parser().parse_args(argv)
    try:
        config = load_config(args.config)
        ground_truth = read_trajectory(args.gt) if args.gt is not None else None
        if args.max_frames is not None and args.max_frames < 1:
            raise InputError("--max-frames must be at least 1")
        if args.map_voxel <= 0:
            raise InputError("--map-voxel must be positive")
        folder, metrics = run_bag(args.bag, args.out, config, args.topic, ground_truth, args.max_frames,
                                  args.map_voxel, progress=not args.quiet)
    except (InputError, BagError, ValueError) as error:
        print(f"sandro-slam: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sandro-slam: aborted", file=sys.stderr)
        return 130
    print_summary(folder, metrics)
    return 0


def load_config(path: Path | None) -> SlamConfig:
    """The SlamConfig in `path` (defaults when None); InputError in one line when it cannot be used."""
    if path is None:
        return SlamConfig()
    if not path.is_file():
        raise InputError(f"no such config file: {path}")
    import pydantic
    import yaml

    try:
        return SlamConfig.from_yaml(path)
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "top level"
        more = f" (and {error.error_count() - 1} more)" if error.error_count() > 1 else ""
        raise InputError(f"{path}: {where}: {first['msg']}{more}") from None


def run_bag(bag: Path, out: Path, config: SlamConfig, topic: str | None = None,
            ground_truth: tuple[np.ndarray | None, np.ndarray] | None = None, max_frames: int | None = None,
            map_voxel: float = 0.2, progress: bool = False) -> tuple[Path, dict]:
    """Run the pipeline over a bag and write a new results folder under `out`; returns it and the metrics.

    Raises:
        BagError: the bag cannot be read (before anything is written).
        InputError: `out` is not writable.
    """
    with BagScans(bag, topic) as scans:
        try:
            folder = new_run_folder(out)
        except OSError as error:
            raise InputError(f"cannot write results under {out}: {error.strerror or error}") from None
        total = len(scans) if max_frames is None else min(len(scans), max_frames)
        reading = _Clock()
        stop = _StopRequest()
        frames = _timed(itertools.islice(scans, total), reading)
        if progress:
            from tqdm import tqdm

            frames = tqdm(frames, total=total, unit="frame", desc="sandro-slam", dynamic_ncols=True)
        start = time.perf_counter()
        try:
            with stop:
                result = OfflineSlam(config).run(stop.until_requested(frames))
            wall = time.perf_counter() - start
            metrics = {
                "bag": str(bag), "topic": scans.topic, "messages": len(scans), "interrupted": stop.requested,
                **_run_metrics(result, wall, reading.seconds),
            }  # fmt: skip
            truth = None
            if ground_truth is not None:
                truth = match_ground_truth(result, *ground_truth)
                metrics["ground_truth"] = evaluate(result, *truth)
        except BaseException:
            folder.rmdir()  # nothing written yet
            raise
    write_results(folder, result, config, metrics, truth, map_voxel)
    link_latest(folder)
    return folder, metrics


def write_results(folder: Path, result: SlamResult, config: SlamConfig, metrics: dict,
                  truth: tuple[np.ndarray, np.ndarray] | None, map_voxel: float) -> None:
    """Every output file of a run (see the module docstring), each written atomically; `truth` is the ground
    truth as `match_ground_truth` returns it."""
    write_trajectories(folder, result)
    write_graph(folder / "graph.g2o", result)
    write_loops(folder / "loops.csv", result)
    metrics["map_points"] = write_map(folder / "map.ply", result, map_voxel)
    plot_trajectories(folder / "trajectory.png", result, truth)
    with atomic_path(folder / "config.yaml") as tmp:
        config.to_yaml(tmp)
    write_session(folder, result)
    write_text_atomic(folder / "metrics.json", json.dumps(metrics, indent=2) + "\n")


def match_ground_truth(result: SlamResult, times: np.ndarray | None,
                       poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mask of the result's frames with a ground-truth pose, those poses). TUM ground truth is interpolated at
    the result's pose times; KITTI ground truth (no times) is taken as one pose per bag message, in order."""
    if times is not None:
        return interpolate_poses(times, poses, result.timestamps, GT_MAX_GAP)
    skipped = set(result.skipped_frames)
    read = len(result.timestamps) + len(skipped)
    indices = np.array([i for i in range(read) if i not in skipped], dtype=int)
    mask = indices < len(poses)
    return mask, poses[indices[mask]]


def evaluate(result: SlamResult, mask: np.ndarray, truth: np.ndarray) -> dict:
    """ATE [m] (RMSE after an SE3 alignment) and RPE [m] over 10 frames, before and after loop closure, on the
    frames in `mask` against their ground-truth poses `truth` (as `match_ground_truth` returns them)."""
    if mask.sum() < 3:
        raise InputError("the ground truth covers fewer than 3 of the processed scans (check its times or format)")
    metrics = {"frames_matched": int(mask.sum())}
    for name, estimate in (("odometry", result.odometry_poses[mask]), ("slam", result.poses[mask])):
        metrics[f"ate_{name}_m"] = ate(estimate, truth)
        metrics[f"rpe_{name}_m"] = rpe(estimate, truth)
    return metrics


def _run_metrics(result: SlamResult, wall: float, read_seconds: float) -> dict:
    frames = len(result.timestamps)
    span = float(result.timestamps[-1] - result.timestamps[0]) if frames > 1 else 0.0
    accepted = sum(loop.weight >= 0.5 for loop in result.loops)
    return {
        "frames": frames,
        "frames_skipped": len(result.skipped_frames),
        "keyframes": len(result.keyframes),
        "loops_verified": len(result.loops),
        "loops_accepted": accepted,
        "loops_rejected": len(result.loops) - accepted,
        "loops_found_by": dict(Counter(loop.found_by for loop in result.loops)),
        "wall_s": wall,
        "frames_per_s": frames / wall if wall > 0 else float("nan"),
        "realtime_factor": span / wall if wall > 0 else float("nan"),
        "bag_read_s": read_seconds,
        "timings_s": result.timings,
    }


def print_summary(folder: Path, metrics: dict) -> None:
    """What a run did, its ATE against the ground truth when known, and where its results are."""
    stopped = " (stopped early by Ctrl-C)" if metrics["interrupted"] else ""
    print(f"{metrics['frames']} scans{stopped}, {metrics['frames_per_s']:.1f} frames/s, {metrics['keyframes']} "
          f"keyframes, {metrics['loops_accepted']} loops accepted, {metrics['loops_rejected']} rejected")
    if "ground_truth" in metrics:
        gt = metrics["ground_truth"]
        print(f"ATE odometry {gt['ate_odometry_m']:.3f} m -> after loop closure {gt['ate_slam_m']:.3f} m "
              f"({gt['frames_matched']} scans matched to the ground truth)")
    print(f"results: {folder}")
    print(f"plot:    {folder / 'trajectory.png'}")


class _Clock:
    seconds = 0.0


def _timed(items: Iterable, clock: _Clock) -> Iterator:
    """Yield from `items`, adding the time spent producing each item to `clock`."""
    iterator = iter(items)
    while True:
        tic = time.perf_counter()
        try:
            item = next(iterator)
        except StopIteration:
            return
        finally:
            clock.seconds += time.perf_counter() - tic
        yield item


class _StopRequest:
    """While active, the first Ctrl-C only asks the frame stream to end; the second raises KeyboardInterrupt."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None

    def __enter__(self) -> "_StopRequest":
        self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        signal.signal(signal.SIGINT, self._previous)

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("\nsandro-slam: stopping after this scan and writing the results (Ctrl-C again to abort)",
              file=sys.stderr, flush=True)

    def until_requested(self, frames: Iterable) -> Iterator:
        """The frames, until a stop is requested."""
        for frame in frames:
            if self.requested:
                return
            yield frame


if __name__ == "__main__":
    sys.exit(main())
