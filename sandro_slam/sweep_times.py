"""Per-point times from the azimuth for raw sweeps of a spinning LiDAR that come without them (`sweep_times`).

A driver that leaves the time field out hands over either raw sweeps (every point where the sensor was when it
fired: smeared by the motion over the sweep) or clouds a LiDAR-inertial front end deskewed, and nothing in one cloud
tells which. Given the sensor's turning direction, each point gets the time at which a sensor turning that way,
once per sweep, starting looking backwards, looks in its direction, and KISS-ICP deskews the sweep with it. The
direction is named in the configuration or told from the first scans (`detected_rotation`): raw sweeps are deskewed
better by one direction than by the other, deskewed clouds made worse by both alike (docs/benchmarks.md, "Raw
sweeps without time"). Not for a swaying sensor (a walker, a hand): deskewing at the constant velocity of the sweep
before adds the sway instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from kiss_icp.config.parser import KISSConfig
from kiss_icp.kiss_icp import KissICP
from scipy.spatial import cKDTree

from sandro_core.geometry import rotation_angle, transform_points
from sandro_slam.scan import Scan
from sandro_slam.sway import SWAY_DEG, sway_deg

Rotation = Literal["clockwise", "counterclockwise"]

TEST_SCANS = 300  # scans without per-point times `detected_rotation` judges: 30 s at 10 Hz (on 100, deskewed clouds
# of a car that started from rest looked raw)
SWAY_SCANS = 50  # scans after which a swaying sensor is told, and the test ends
TEST_POINTS = 32768  # a denser scan is thinned to every k-th point for the test (128 beams: every fourth, which
# told raw from deskewed as all points did, in two thirds of the time)
TEST_WARMUP = 10  # scans each of its runs registers before their residuals count
TEST_STRIDE = 3  # the residual of every third scan after them counts
MIN_TEST_SCANS = 10  # residuals of a moving sensor below which the test does not judge
MOVING_VOXELS = 0.1  # a scan's residual counts where the sensor moved more than this many odometry voxels over the
MOVING_DEG = 0.5  # sweep before, or turned more than this [deg]: standing still, deskewing changes nothing
MIN_ASYMMETRY = 0.15  # share of scans one direction deskews better than the plain run less the other direction's
# share, from which the scans are raw sweeps: 0.27-0.78 on raw sweeps of cars, at most 0.04 on deskewed clouds and
# on raw sweeps of a Livox-Avia-like rosette, whose order is no azimuth's (docs/benchmarks.md)


def azimuth_times(points: np.ndarray, period: float, rotation: Rotation) -> np.ndarray:
    """(N,) per-point times [s] of a spinning sensor's sweep for `points` (N, 3) in the sensor frame: the sweep starts
    looking backwards (azimuth pi, KISS-ICP's KITTI convention) and turns once in `period` [s], `rotation` seen from
    above."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    turned = np.pi - azimuth if rotation == "clockwise" else azimuth + np.pi
    return np.mod(turned / (2.0 * np.pi), 1.0) * period


def with_azimuth_times(scan: Scan, period: float, rotation: Rotation | None) -> Scan:
    """`scan` with `azimuth_times` where it has no per-point times and `rotation` is set; else as it is."""
    if rotation is None or len(scan.times) or not len(scan.points):
        return scan
    return Scan(scan.timestamp, scan.points, azimuth_times(scan.points, period, rotation))


def sweep_period(stamps: Sequence[float]) -> float:
    """The median spacing [s] of consecutive scan stamps: one turn of the sensor (0.1 s with fewer than two)."""
    steps = np.diff(np.asarray(stamps, dtype=np.float64))
    steps = steps[steps > 0.0]
    return float(np.median(steps)) if len(steps) else 0.1


def detected_rotation(scans: Sequence[np.ndarray], odometry: KISSConfig, period: float) -> Rotation | None:
    """The turning direction whose azimuth times deskew `scans` ((N, 3) points each in the sensor frame, without
    per-point times, in order, one every `period` [s]) where they look like raw sweeps of a spinning sensor that does
    not sway; None where they look deskewed, where the sensor sways, or with fewer than MIN_TEST_SCANS residuals
    of a moving sensor.

    KISS-ICP (`odometry`) runs over the scans as they are; where its poses sway (`sway_deg` above SWAY_DEG: a
    walker, a hand; judged after SWAY_SCANS scans already) None. Then two more runs, the scans deskewed with
    clockwise and with counter-clockwise azimuth times. Each run's residual at a scan is the median distance of its
    registered points to the nearest point of its map before the scan. A direction is taken where the share of
    scans it deskews better than the plain run exceeds the other direction's by MIN_ASYMMETRY: on deskewed clouds
    both directions make most scans worse, about as often; on raw sweeps the right one makes most better and the
    wrong one few. Only the residuals of scans over which the sensor moved count (`_moving`)."""
    plain = _ResidualRun(odometry, period, None)
    for index, points in enumerate(scans):
        plain.add(points)
        if index + 1 == SWAY_SCANS and sway_deg(plain.poses) > SWAY_DEG:
            return None
    moving = _moving(plain.poses, odometry.mapping.voxel_size)[plain.measured] & np.isfinite(plain.residuals)
    if np.count_nonzero(moving) < MIN_TEST_SCANS or sway_deg(plain.poses) > SWAY_DEG:
        return None
    shares = {}
    for rotation in ("clockwise", "counterclockwise"):
        run = _ResidualRun(odometry, period, rotation)
        for points in scans:
            run.add(points)
        shares[rotation] = float(np.mean(run.residuals[moving] < plain.residuals[moving]))
    better = max(shares, key=shares.get)
    return better if 2.0 * shares[better] - sum(shares.values()) >= MIN_ASYMMETRY else None


def _moving(poses: np.ndarray, voxel: float) -> np.ndarray:
    """(F,) whether the sensor moved over each sweep, poses (F, 4, 4) T_world_sensor: more than MOVING_VOXELS x
    `voxel` [m] or MOVING_DEG since the pose before (the first: False)."""
    motions = np.linalg.inv(poses[:-1]) @ poses[1:]
    moved = (np.linalg.norm(motions[:, :3, 3], axis=1) > MOVING_VOXELS * voxel) | (
        rotation_angle(motions[:, :3, :3]) > np.radians(MOVING_DEG)
    )
    return np.concatenate([[False], moved])


class _ResidualRun:
    """KISS-ICP over scans given one by one, with azimuth times turning `rotation` (None: none): its poses
    (`poses`, (F, 4, 4) T_world_sensor), and at every TEST_STRIDE-th scan from the TEST_WARMUP-th the median
    distance [m] of its registered points to the nearest point of the map before it (`residuals`; distances capped
    at three of KISS-ICP's adaptive thresholds; NaN where the map or the scan is empty)."""

    def __init__(self, odometry: KISSConfig, period: float, rotation: Rotation | None):
        self.kiss_icp = KissICP(odometry)
        self.period, self.rotation = period, rotation
        self._poses: list[np.ndarray] = []
        self._residuals: list[float] = []

    @property
    def poses(self) -> np.ndarray:
        return np.asarray(self._poses).reshape(-1, 4, 4)

    @property
    def residuals(self) -> np.ndarray:
        return np.asarray(self._residuals)

    @property
    def measured(self) -> np.ndarray:
        """The indices of the scans `residuals` belong to."""
        return np.arange(TEST_WARMUP, len(self._poses), TEST_STRIDE)[: len(self._residuals)]

    def add(self, points: np.ndarray) -> None:
        """Register the next scan, (N, 3) points in its sensor frame (every k-th of them: at most TEST_POINTS)."""
        kiss_icp, index = self.kiss_icp, len(self._poses)
        points = points[:: -(-len(points) // TEST_POINTS) or 1]
        times = np.empty(0) if self.rotation is None else azimuth_times(points, self.period, self.rotation)
        measured = index >= TEST_WARMUP and (index - TEST_WARMUP) % TEST_STRIDE == 0
        if measured:
            map_points = kiss_icp.local_map.point_cloud()
            bound = 3.0 * kiss_icp.adaptive_threshold.get_threshold()
        source = kiss_icp.register_frame(points, times)[1]
        self._poses.append(kiss_icp.last_pose.copy())
        if measured and len(map_points) and len(source):
            tree = cKDTree(map_points, balanced_tree=False, compact_nodes=False)
            distances = tree.query(transform_points(kiss_icp.last_pose, source), distance_upper_bound=bound)[0]
            self._residuals.append(float(np.median(np.minimum(distances, bound))))
        elif measured:
            self._residuals.append(np.nan)
