"""One sandro-slam run: a bag streamed through OfflineSlam into a new results folder (`io.slam_results`)."""

from __future__ import annotations

import itertools
import signal
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from pipelines.evaluation import evaluate, match_ground_truth
from pipelines.io.atomic import link_latest, new_run_folder
from pipelines.io.bags import BagScans
from pipelines.io.slam_results import write_results
from sandro_slam import OfflineSlam, SlamConfig, SlamResult

GT_MAX_GAP = 0.25  # [s] ground-truth samples farther apart than this are not interpolated between


def run_bag(
    bag: Path,
    out: Path,
    config: SlamConfig,
    topic: str | None = None,
    ground_truth: tuple[np.ndarray | None, np.ndarray] | None = None,
    max_frames: int | None = None,
    map_voxel: float = 0.2,
    progress: bool = False,
) -> tuple[Path, dict]:
    """Run the pipeline over a bag and write a new results folder under `out`; returns it and the metrics.

    `ground_truth`: (times or None, poses) as `io.trajectory.read_trajectory` returns them. While it runs, the
    first Ctrl-C stops reading the bag (what was read is still optimised and written), the second raises
    KeyboardInterrupt.

    Raises:
        BagError: the bag cannot be read (before anything is written).
        OSError: `out` is not writable.
        ValueError: the ground truth covers fewer than 3 scans (nothing is written).
    """
    with BagScans(bag, topic) as scans:
        try:
            folder = new_run_folder(out)
        except OSError as error:
            raise OSError(f"cannot write results under {out}: {error.strerror or error}") from None
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
                **run_metrics(result, wall, reading.seconds),
            }  # fmt: skip
            truth = None
            if ground_truth is not None:
                truth = match_ground_truth(result, *ground_truth, max_gap=GT_MAX_GAP)
                metrics["ground_truth"] = evaluate(result, *truth)
        except BaseException:
            folder.rmdir()  # nothing written yet
            raise
    write_results(folder, result, config, metrics, truth, map_voxel)
    link_latest(folder)
    return folder, metrics


def run_metrics(result: SlamResult, wall: float, read_seconds: float) -> dict:
    """Counts and speed of a run: frames, keyframes, loops, frames/s, real-time factor and timings [s]."""
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

    def __enter__(self) -> _StopRequest:
        self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
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
