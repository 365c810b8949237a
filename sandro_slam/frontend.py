"""The SLAM front end: scans -> KISS-ICP poses -> keyframes with submaps, handed to a loop closer as they close."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from sandro_slam.config import SlamConfig
from sandro_slam.keyframes import Keyframe, KeyframeBuilder, voxel_downsample
from sandro_slam.odometry import ScanOdometry, path_length, reregister_start
from sandro_slam.scan import Scan
from sandro_slam.timing import Stopwatch

MAX_HELD_SCANS = 300  # a start that stands still longer (30 s at 10 Hz) is not held back any further


class LoopCloser(Protocol):
    """What takes the completed keyframes: a LoopClosureModule, or its worker process."""

    def add_keyframe(self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray) -> object: ...


class Frontend:
    """Registers scans with KISS-ICP, cuts the trajectory into keyframes and hands each completed keyframe to the
    loop closer.

    The scans of the first two keyframe distances are held back until the start is re-registered
    (`reregister_start`); later poses get the same correction. After `finish`: `timestamps` (the time each pose
    refers to: stamp + latest per-point time, where KISS-ICP deskews to), `poses` (T_world_sensor),
    `keyframe_of_frame` and `keyframes`. `stopwatch` adds up wall seconds of "odometry" and "loop_closure" (the
    keyframe work done in this process).
    """

    def __init__(self, config: SlamConfig, closer: LoopCloser, stopwatch: Stopwatch | None = None):
        self.config = config
        self.closer = closer
        self.odometry = ScanOdometry(config.odometry)
        self.builder = KeyframeBuilder(config.keyframes)
        # The scan as the submaps take it: KISS-ICP's own voxelisation when that is fine enough.
        self._own_scan = config.keyframes.submap_voxel >= 0.5 * config.odometry.mapping.voxel_size
        self.timestamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.keyframe_of_frame: list[int] = []
        self.keyframes: list[Keyframe] = []
        self.stopwatch = stopwatch or Stopwatch("odometry", "loop_closure")
        self._held: list[tuple[float, np.ndarray, np.ndarray]] = []  # (stamp, pose, scan) of the start
        self._correction: np.ndarray | None = None  # KISS-ICP's frame -> the re-registered start's, once known

    def add(self, scan: Scan) -> None:
        """Register a scan with finite points and keep its pose (held back while the start is not re-registered)."""
        with self.stopwatch("odometry"):
            deskewed, _ = self.odometry.register_frame(scan.points, scan.times)
            pose = self.odometry.last_pose.copy()
        deskews = len(scan.times) > 0 and self.config.odometry.data.deskew
        stamp = scan.timestamp + (float(scan.times.max()) if deskews else 0.0)
        points = (
            self.odometry.map_points
            if self._own_scan
            else voxel_downsample(deskewed, self.config.keyframes.submap_voxel)
        )
        if self._correction is not None:
            self._keep(stamp, self._correction @ pose, points)
            return
        self._held.append((stamp, pose, points))
        held_poses = np.array([held[1] for held in self._held])
        if len(self._held) >= MAX_HELD_SCANS or path_length(held_poses)[-1] >= 2.0 * self.config.keyframes.distance:
            self._release_start()

    def finish(self) -> None:
        """Release a start still held and close the last keyframe. ValueError when no scan was added."""
        if self._correction is None and self._held:
            self._release_start()
        if not self.timestamps:
            raise ValueError("no frame with finite points: nothing to process")
        with self.stopwatch("loop_closure"):
            last = self.builder.flush()
            if last is not None:
                self._close(last)

    def _release_start(self) -> None:
        """Re-register the held scans, keep them, and the correction that maps later KISS-ICP poses alike."""
        stamps, poses, scans = zip(*self._held)
        with self.stopwatch("odometry"):
            fixed = reregister_start(self.odometry, np.asarray(poses), list(scans), self.config.keyframes.distance)
        for stamp, pose, points in zip(stamps, fixed, scans):
            self._keep(stamp, pose, points)
        self._correction = fixed[-1] @ np.linalg.inv(poses[-1])
        self._held = []

    def _keep(self, stamp: float, pose: np.ndarray, points: np.ndarray) -> None:
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
