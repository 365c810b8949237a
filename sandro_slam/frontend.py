"""The SLAM front end: scans -> odometry poses -> keyframes with submaps, handed to a loop closer as they close."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from sandro_slam.config import SlamConfig
from sandro_slam.keyframes import Keyframe, KeyframeBuilder
from sandro_slam.odometry import GivenOdometry, GivenPoses, KissIcpOdometry, OdometryPose
from sandro_slam.scan import Scan
from sandro_slam.timing import Stopwatch


class LoopCloser(Protocol):
    """What takes the completed keyframes: a LoopClosureModule, or its worker process."""

    def add_keyframe(self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray) -> object: ...


class Frontend:
    """Turns scans into odometry poses (KISS-ICP, or `given` poses of another front end), cuts the trajectory into
    keyframes and hands each completed keyframe to the loop closer.

    After `finish`: `timestamps` (the time each pose refers to: with KISS-ICP the stamp + the middle of the first
    and last per-point time, where the scans are deskewed to; with given poses the stamp), `poses`
    (T_world_sensor), `keyframe_of_frame`, `keyframes`, and `unmatched`: the indices of the scans added that the
    given poses do not cover. `stopwatch` adds up wall seconds of "odometry" and "loop_closure" (the keyframe work
    done in this process).
    """

    def __init__(
        self,
        config: SlamConfig,
        closer: LoopCloser,
        stopwatch: Stopwatch | None = None,
        given: GivenPoses | None = None,
    ):
        self.config = config
        self.closer = closer
        self.odometry = (
            KissIcpOdometry(config)
            if given is None
            else GivenOdometry(given, config.keyframes.submap_voxel, config.odometry.data.deskew)
        )
        self.builder = KeyframeBuilder(config.keyframes)
        self.timestamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.keyframe_of_frame: list[int] = []
        self.keyframes: list[Keyframe] = []
        self.stopwatch = stopwatch or Stopwatch("odometry", "loop_closure")

    @property
    def unmatched(self) -> list[int]:
        return self.odometry.unmatched

    def add(self, scan: Scan) -> None:
        """Add a scan with finite points."""
        with self.stopwatch("odometry"):
            ready = self.odometry.add(scan)
        self._keep(ready)

    def skip(self, stamp: float) -> None:
        """A scan at `stamp` [s] that is not added (too sparse to register): the odometry learns that it passed."""
        self.odometry.skip(stamp)

    def finish(self) -> None:
        """Keep the poses the odometry still holds and close the last keyframe. ValueError when there is none."""
        with self.stopwatch("odometry"):
            ready = self.odometry.finish()
        self._keep(ready)
        if not self.timestamps:
            raise ValueError("no frame with enough finite points (and an odometry pose): nothing to process")
        with self.stopwatch("loop_closure"):
            last = self.builder.flush()
            if last is not None:
                self._close(last)

    def _keep(self, ready: list[OdometryPose]) -> None:
        for stamp, pose, points in ready:
            with self.stopwatch("loop_closure"):
                completed = self.builder.add_scan(len(self.timestamps), pose, points)
                if completed is not None:
                    self._close(completed)
            self.timestamps.append(stamp)
            self.poses.append(pose)
            self.keyframe_of_frame.append(self.builder.current_key())

    def _close(self, keyframe: Keyframe) -> None:
        self.keyframes.append(keyframe)
        self.closer.add_keyframe(keyframe.key, keyframe.T_world_keyframe, keyframe.points)
