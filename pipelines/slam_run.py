"""One sandro-slam run: an input streamed through OfflineSlam into a new results folder (`io.slam_results`)."""

from __future__ import annotations

import itertools
import signal
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipelines.evaluation import evaluate, match_ground_truth
from pipelines.io.atomic import link_latest, new_run_folder
from pipelines.io.inputs import Poses, open_input
from pipelines.io.slam_results import write_results
from pipelines.scan_frame import centres_kept, stands_still_in_a_fixed_frame, warn_frame, watched_for_world_frame
from sandro_slam import GivenPoses, OfflineSlam, SlamConfig, SlamResult
from sandro_slam.refine import pays

GT_MAX_GAP = 0.25  # [s] ground-truth samples farther apart than this are not interpolated between


def run_input(
    path: Path,
    out: Path,
    config: SlamConfig,
    fmt: str | None = None,
    topic: str | None = None,
    rate: float | None = None,
    ground_truth: Poses | None = None,
    odometry: Poses | None = None,
    max_frames: int | None = None,
    map_voxel: float = 0.2,
    progress: bool = False,
    ctrl_c: bool = True,
) -> tuple[Path, dict]:
    """Run the pipeline over an input (`io.inputs.open_input(path, fmt, topic, rate)`) and write a new results
    folder under `out`; returns it and the metrics.

    `ground_truth` and `odometry`: (times or None, poses) as `io.trajectory.read_trajectory` returns them; None takes
    what came with the input (a KITTI sequence's poses.txt, a keyframe dump's poses), if anything. With odometry its
    poses replace KISS-ICP's (matched to the scans by time, or one per scan in order). While it runs, with `ctrl_c`
    (in the main thread only), the first Ctrl-C stops reading (what was read is still optimised and written), the
    second raises KeyboardInterrupt.

    Raises:
        ValueError (BagError for bags): the input cannot be read, or the odometry does not fit it (before anything
            is written); the ground truth covers fewer than 3 scans (nothing is written).
        OSError: `out` is not writable.
    """
    with open_input(path, fmt, topic, rate) as source:
        ground_truth = ground_truth if ground_truth is not None else source.ground_truth
        given = _given_poses(odometry if odometry is not None else source.odometry, len(source.scans))
        notes = list(source.notes)
        if source.pose_topics and given is None:
            listing = ", ".join(f"{name} ({kind.replace('/msg/', '/')})" for name, kind in source.pose_topics.items())
            notes.append(
                f"the bag also holds poses: {listing}; --odometry TOPIC takes them instead of KISS-ICP's (the scans "
                "in the frame of those poses), --gt TOPIC compares with them"
            )
        for note in notes:
            print(f"sandro-slam: {note}", file=sys.stderr, flush=True)
        try:
            folder = new_run_folder(out)
        except OSError as error:
            raise OSError(f"cannot write results under {out}: {error.strerror or error}") from None
        total = len(source.scans) if max_frames is None else min(len(source.scans), max_frames)
        reading = _Clock()
        stop = _StopRequest(ctrl_c)
        frames = _timed(itertools.islice(source.scans, total), reading)
        centres: list[np.ndarray | None] = []
        frames = watched_for_world_frame(frames, given) if given is not None else centres_kept(frames, centres)
        if progress:
            from tqdm import tqdm

            frames = tqdm(frames, total=total, unit="frame", desc="sandro-slam", dynamic_ncols=True)
        start = time.perf_counter()
        try:
            with stop:
                slam = OfflineSlam(config)
                result = slam.run(stop.until_requested(frames), odometry=given)
                refine = pays(result.config.refine, result.odometry_poses) and not stop.requested
                if refine:
                    again = _timed(itertools.islice(source.scans, total), reading)
                    try:
                        result = slam.refine(stop.until_requested(again), result, progress)
                    except ValueError:
                        if not stop.requested:
                            raise  # a scan that cannot be read again; stopped: the first pass is written
                        refine = False
                result = replace(result, config=result.config.model_copy(update={"refine": refine}))  # as run
            wall = time.perf_counter() - start
            if "sweep_test" in result.timings:
                print(f"sandro-slam: {sweep_times_note(result.config.sweep_times)}", file=sys.stderr, flush=True)
            if centres and stands_still_in_a_fixed_frame(centres, result):
                warn_frame("the scans seem to be in a fixed world frame, not the sensor's (their centres travel, "
                           "KISS-ICP's odometry stays put)")  # fmt: skip
            metrics = {
                **source.description, "odometry": "given" if given else "kiss-icp", "interrupted": stop.requested,
                **run_metrics(result, wall, reading.seconds),
            }  # fmt: skip
            truth = None
            if ground_truth is not None:
                truth = match_ground_truth(result, *ground_truth, max_gap=GT_MAX_GAP)
                metrics["ground_truth"] = evaluate(result, *truth)
        except BaseException:
            folder.rmdir()  # nothing written yet
            raise
    write_results(folder, result, result.config, metrics, truth, map_voxel)
    link_latest(folder)
    return folder, metrics


def _given_poses(odometry: Poses | None, scans: int) -> GivenPoses | None:
    """The odometry as GivenPoses; ValueError when, one pose per scan, their counts differ."""
    if odometry is None:
        return None
    times, poses = odometry
    if times is None and len(poses) != scans:
        raise ValueError(f"the odometry has {len(poses)} poses for {scans} scans (one per scan, or give times: TUM)")
    return GivenPoses(poses, times)


def sweep_times_note(sweep_times: str) -> str:
    """What `sweep_times: auto` made of scans without per-point times, and how to override it."""
    if sweep_times == "none":
        return ("the scans have no per-point times and look deskewed (or the sensor sways): taken as they are; "
                "--sweep-times clockwise if they are raw sweeps of a spinning LiDAR")  # fmt: skip
    return (f"the scans have no per-point times and look like raw sweeps turning {sweep_times}: deskewed with times "
            "from the azimuth; --sweep-times none to take them as they are")  # fmt: skip


def run_metrics(result: SlamResult, wall: float, read_seconds: float) -> dict:
    """Counts and speed of a run: frames, keyframes, loops, frames/s, real-time factor, reading and stage times [s]."""
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
        "odometry_noise_scale": result.odometry_noise_scale,
        "wall_s": wall,
        "frames_per_s": frames / wall if wall > 0 else float("nan"),
        "realtime_factor": span / wall if wall > 0 else float("nan"),
        "read_s": read_seconds,
        "timings_s": result.timings,
    }


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
    """While active, the first Ctrl-C only asks the frame stream to end; the second raises KeyboardInterrupt.
    Not `listening`: Ctrl-C keeps its handler (a worker of a batch, where the driver decides)."""

    def __init__(self, listening: bool = True) -> None:
        self.requested = False
        self._listening = listening
        self._previous = None

    def __enter__(self) -> _StopRequest:
        if self._listening:
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._listening:
            signal.signal(signal.SIGINT, self._previous)

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print(
            "\nsandro-slam: stopping after this scan and writing the results (Ctrl-C again to abort)",
            file=sys.stderr,
            flush=True,
        )

    def until_requested(self, frames: Iterable) -> Iterator:
        """The frames, until a stop is requested."""
        for frame in frames:
            if self.requested:
                return
            yield frame
