"""Whether the scans handed to sandro-slam are in the sensor frame: the check of their centres against the odometry
(`ScanFrameCheck`), and the stream wrappers and warnings `slam_run.run_input` uses it through."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator

import numpy as np

from sandro_slam import GivenPoses, SlamResult


class ScanFrameCheck:
    """Tells whether the scans are in a world frame instead of the sensor frame, the two ways a world-frame topic
    (FAST-LIO2's /cloud_registered picked instead of /cloud_registered_body) shows:
    - with a given odometry, each scan would be moved by its pose a second time (`world_frame`);
    - with KISS-ICP, the scans line up where they are: the odometry stands still while their centres travel
      (`fixed_frame`).

    Reads each scan's centre c (mean point) with its odometry pose (R, t) as given (sensor frame) and as R^T (c - t)
    (world frame). In the scans' true frame the centre stays near the sensor while the drive moves on; read in the
    other frame it travels with the drive. Over at least `MIN_SCANS` scans whose centres as given vary by more than
    `MIN_SPREAD` (rms about their mean): `world_frame` where the other reading varies less than half as much,
    `fixed_frame` where the odometry's positions do.
    """

    MIN_SCANS = 50
    MIN_SPREAD = 10.0  # [m]

    def __init__(self) -> None:
        self._count = 0
        self._mean = np.zeros((3, 3))  # running mean of each reading [m]: the centre, as given and in the world; t
        self._mean_square = np.zeros(3)  # running mean of each reading's squared norm [m^2]

    def add(self, centre: np.ndarray | None, pose: np.ndarray) -> None:
        """Take a scan's centre (`scan_centre`; None: a scan without points) and its odometry pose T_world_sensor."""
        if centre is None:
            return
        readings = np.stack([centre, pose[:3, :3].T @ (centre - pose[:3, 3]), pose[:3, 3]])
        self._count += 1
        self._mean += (readings - self._mean) / self._count
        self._mean_square += (np.einsum("ij,ij->i", readings, readings) - self._mean_square) / self._count

    def _spreads(self) -> np.ndarray | None:
        if self._count < self.MIN_SCANS:
            return None
        spreads = np.sqrt(np.maximum(self._mean_square - np.einsum("ij,ij->i", self._mean, self._mean), 0.0))
        return spreads if spreads[0] > self.MIN_SPREAD else None

    @property
    def world_frame(self) -> bool:
        spreads = self._spreads()
        return spreads is not None and spreads[1] < 0.5 * spreads[0]

    @property
    def fixed_frame(self) -> bool:
        spreads = self._spreads()
        return spreads is not None and spreads[2] < 0.5 * spreads[0]


def scan_centre(points: np.ndarray) -> np.ndarray | None:
    """The mean (3,) of the finite points (N, 3) [m]; None without any."""
    points = np.asarray(points)
    finite = points[np.isfinite(points).all(axis=1)]
    return finite.mean(axis=0) if len(finite) else None


def watched_for_world_frame(frames: Iterable, given: GivenPoses) -> Iterator:
    """The frames, unchanged; a warning on stderr the first time they look like world-frame scans of the given
    odometry (`ScanFrameCheck.world_frame`)."""
    check, warned = ScanFrameCheck(), False
    for index, frame in enumerate(frames):
        pose = None if warned else given.at(index, frame.timestamp)
        if pose is not None:
            check.add(scan_centre(frame.points), pose)
            if check.world_frame:
                warned = True
                warn_frame("the scans seem to be in the odometry's world frame, not the sensor's (their centres "
                           "follow the poses)")  # fmt: skip
        yield frame


def centres_kept(frames: Iterable, centres: list[np.ndarray | None]) -> Iterator:
    """The frames, unchanged; each frame's `scan_centre` appended to `centres`."""
    for frame in frames:
        centres.append(scan_centre(frame.points))
        yield frame


def warn_frame(what: str) -> None:
    """A warning on stderr that the scans are not in the sensor frame: `what` shows, and what to give instead."""
    print(
        f"sandro-slam: warning: {what}: give the scans in the sensor frame (FAST-LIO2: /cloud_registered_body, "
        "LIO-SAM: /lio_sam/deskew/cloud_deskewed)",
        file=sys.stderr,
        flush=True,
    )


def stands_still_in_a_fixed_frame(centres: list[np.ndarray | None], result: SlamResult) -> bool:
    """`ScanFrameCheck.fixed_frame` over the frames `result` kept (`centres` of every frame read, in order)."""
    skipped = set(result.skipped_frames)
    kept = [centre for index, centre in enumerate(centres) if index not in skipped]
    check = ScanFrameCheck()
    for centre, pose in zip(kept, result.odometry_poses):
        check.add(centre, pose)
    return check.fixed_frame
