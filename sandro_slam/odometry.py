"""Odometry for the SLAM front end: KISS-ICP over the scans, or the poses of another front end.

Both give, scan by scan, what the keyframes are built from: (stamp [s] the pose refers to, T_world_sensor, the
scan's points in the sensor frame at that pose, voxelised no coarser than the submaps). KISS-ICP's poses refer to
the middle of each sweep (`deskew_to_middle`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np
import small_gicp
from kiss_icp.config.parser import KISSConfig
from kiss_icp.kiss_icp import KissICP
from kiss_icp.mapping import get_voxel_hash_map
from kiss_icp.preprocess import Preprocessor

from sandro_core.geometry import interpolate_poses, rotation_angle, transform_points
from sandro_slam.config import OdometryGicpConfig, SlamConfig
from sandro_slam.keyframes import voxel_downsample
from sandro_slam.scan import Scan
from sandro_slam.sweep_rotation import TRIAL_STRIDE, MapFit, OffPredictionWatch, best_sweep_rotation, turned

OdometryPose = tuple[float, np.ndarray, np.ndarray]  # (stamp [s], T_world_sensor, points in the sensor frame)
MAX_HELD_SCANS = 300  # a start that stands still longer (30 s at 10 Hz) is not held back any further
REDESKEW_DEG = 0.5  # deskew and register a scan again when its rotation differs from the prediction by more
PERIOD_SCANS = 10  # the sweep period is the median stamp step over this many scans before
MAX_BRIDGED_SWEEPS = 10  # a longer step between stamps is taken for a jump of the clock (a driver's switch to
# PTP time) or a pause of the recording, not for lost sweeps: the scan is predicted one sweep ahead
DESKEW_STEP = 1e-4  # [s] per-point times are rounded to this when deskewed along given poses


class GaussianMapRefiner:
    """Poses refined with VGICP (small_gicp) against a map of Gaussian voxels built from the scans registered so
    far; voxels not matched for 100 scans are dropped.

    KISS-ICP matches points to points. Where the sensor's pattern repeats rotated from sweep to sweep (a Livox
    Mid-360's zigzag, an Avia's rosette) and the map holds little more than the last sweeps' lines, the nearest
    points are those of the same lines one sweep before, and point-to-point ICP follows the pattern: a walker
    with a Mid-360-like sensor turned 1.4 deg a sweep that it never turned. A voxel's Gaussian sums the points of
    many lines, whatever their pattern, so VGICP aligns the scan with the surfaces instead."""

    def __init__(self, config: OdometryGicpConfig):
        self.config = config
        self.map = small_gicp.GaussianVoxelMap(config.resolution)
        self.map.set_lru(horizon=100, clear_cycle=10)

    def prepared(self, points: np.ndarray) -> small_gicp.PointCloud:
        """`points` (N, 3) [m] as the map takes them (`insert`): downsampled to `source_voxel`, with their 10
        neighbours' covariances."""
        return small_gicp.preprocess_points(points, self.config.source_voxel, num_neighbors=10, num_threads=1)[0]

    def align(
        self, points: np.ndarray, guess: np.ndarray
    ) -> tuple[np.ndarray, small_gicp.PointCloud, np.ndarray | None]:
        """T_map_scan of a scan (`points` (N, 3) [m] in its frame), refined from `guess` (`register`), the scan as
        the map takes it (`prepared`), and VGICP's Gauss-Newton Hessian at the pose (6x6, right perturbation in
        the order [rotation, translation]; None while the map is empty)."""
        cloud = self.prepared(points)
        result = self._aligned(cloud, guess)
        if result is None:
            return guess, cloud, None
        return result.T_target_source, cloud, np.asarray(result.H)

    def register(self, cloud: small_gicp.PointCloud, guess: np.ndarray) -> tuple[np.ndarray, int]:
        """T_map_scan of a `prepared` scan refined from `guess` (`guess` itself while the map is empty), and how many
        of its points found a voxel within `max_distance` at the end (0 while the map is empty)."""
        result = self._aligned(cloud, guess)
        return (guess, 0) if result is None else (result.T_target_source, result.num_inliers)

    def _aligned(self, cloud: small_gicp.PointCloud, guess: np.ndarray) -> small_gicp.RegistrationResult | None:
        if not (self.map.size() and cloud.size()):
            return None
        return small_gicp.align(
            self.map,
            cloud,
            guess,
            max_correspondence_distance=self.config.max_distance,
            num_threads=1,  # KISS-ICP and the loop-closure worker keep the other cores busy: more threads wait
            max_iterations=self.config.max_iterations,
        )

    def insert(self, cloud: small_gicp.PointCloud, pose: np.ndarray) -> None:
        """Add a `prepared` scan to the map at `pose` (T_map_scan)."""
        self.map.insert(cloud, pose)


@dataclass(frozen=True)
class RegisteredScan:
    """A scan deskewed with one motion and registered: T_world_sensor, the deskewed points (sensor frame), KISS-ICP's
    voxelisations of them (registration source, map points), the Gaussian map's (None without VGICP) and VGICP's
    Hessian at the pose (`GaussianMapRefiner.align`; None without VGICP or while its map is empty)."""

    pose: np.ndarray
    deskewed: np.ndarray
    source: np.ndarray
    map_points: np.ndarray
    gicp_cloud: small_gicp.PointCloud | None = None
    hessian: np.ndarray | None = None


class ScanOdometry(KissICP):
    """KISS-ICP that deskews a scan again when its rotation turned out other than predicted, and keeps the
    deskewed scan it voxelised for its map (`map_points`, at half its voxel size, in the scan frame): the keyframe
    submaps take it rather than voxelising the scan again.

    KISS-ICP deskews a scan with the motion of the scan before (constant velocity). Where the rotation rate
    changes within a sweep (a car turning into a sharp corner, the yaw sway of a walker) the scan stays bent by
    the difference, and so does its registered pose. When the registered rotation over the sweep differs from the
    predicted one by more than REDESKEW_DEG, the scan is deskewed again with the registered rotation (the
    translation stays the predicted one: along a corridor or a lane of pillars the registered translation is
    the least certain part, and deskewing with it fed that back) and registered again from where the first
    registration ended.

    The kernel (a third of the correspondence distance) is never below one voxel: on a straight, steady drive
    KISS-ICP's adaptive threshold shrinks until a sharp corner's first scans, turned 5.7 deg beyond the
    prediction, find correspondences only on the ground, which does not see yaw (a 128-beam drive missed 30 deg
    of a corner that way).

    With `gicp` enabled, each pose is then refined with VGICP against a map of Gaussian voxels
    (`GaussianMapRefiner`), and KISS-ICP's map and motion model take the refined pose, held to the prediction along
    the translation directions VGICP's Hessian says the scan constrains weakly (`with_motion_prior`).

    Where the rotation rate steps by more than the second deskewing follows, the pose lies far from its
    prediction compared with the scans before (`OffPredictionWatch`); the scan is then deskewed with other
    rotations over its sweep, each registered, and the one that fits KISS-ICP's map best is refined and kept
    where it still fits better than the prediction's (`sweep_rotation`).

    `sweeps` > 1 says that many sweeps passed since the scan before (the messages between were lost or skipped):
    the prediction is the constant velocity carried over all of them, and the motion model keeps one sweep's."""

    def __init__(self, config: KISSConfig, gicp: OdometryGicpConfig | None = None):
        super().__init__(config)
        self.refiner = GaussianMapRefiner(gicp) if gicp is not None and gicp.enabled else None
        self.watch = OffPredictionWatch()

    def register_frame(
        self, frame: np.ndarray, timestamps: np.ndarray, sweeps: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        sigma = max(self.adaptive_threshold.get_threshold(), self.config.mapping.voxel_size)
        prediction = self.last_pose @ motion_power(self.last_delta, sweeps)
        scan = self._registered(frame, timestamps, self.last_delta, prediction, sigma)
        motion = self._motion(scan.pose, sweeps)
        deskews = len(timestamps) > 0 and self.config.data.deskew
        if deskews and rotation_angle(self.last_delta[:3, :3].T @ motion[:3, :3]) > np.radians(REDESKEW_DEG):
            motion[:3, 3] = self.last_delta[:3, 3]
            scan = self._registered(frame, timestamps, motion, scan.pose, sigma)
        scan = self._refined(scan)
        if self.watch.flags(prediction, scan.pose) and deskews:  # every pose joins the watch's history
            scan = self._sweep_searched(frame, timestamps, scan, sigma)
        pose, self.map_points = scan.pose, scan.map_points
        if scan.hessian is not None:
            pose = with_motion_prior(pose, prediction, scan.hessian, self.refiner.config.motion_prior)
        if self.refiner is not None:
            self.refiner.insert(scan.gicp_cloud, pose)
        self.adaptive_threshold.update_model_deviation(np.linalg.inv(prediction) @ pose)
        self.local_map.update(self.map_points, pose)
        self.last_delta = self._motion(pose, sweeps)
        self.last_pose = pose
        return scan.deskewed, scan.source

    def _motion(self, pose: np.ndarray, sweeps: int) -> np.ndarray:
        """One sweep's motion (4x4) from the last pose to `pose` (T_world_sensor), `sweeps` sweeps later."""
        return motion_power(np.linalg.inv(self.last_pose) @ pose, 1.0 / sweeps)

    def _registered(
        self,
        frame: np.ndarray,
        timestamps: np.ndarray,
        motion: np.ndarray,
        start: np.ndarray,
        sigma: float,
        stride: int = 1,
    ) -> RegisteredScan:
        """The scan deskewed with `motion` (its sweep's, 4x4), voxelised and registered onto KISS-ICP's map from
        `start` (T_world_sensor) with kernel `sigma` [m], every `stride`-th point of its source taking part."""
        deskewed = deskew_to_middle(self.preprocessor, frame, timestamps, motion, self.config.data.deskew)
        source, map_points = self.voxelize(deskewed)
        pose = self.registration.align_points_to_map(source[::stride], self.local_map, start, 3.0 * sigma, sigma)
        return RegisteredScan(pose, deskewed, source, map_points)

    def _refined(self, scan: RegisteredScan) -> RegisteredScan:
        """`scan` with its pose refined by VGICP (as it was without)."""
        if self.refiner is None:
            return scan
        pose, cloud, hessian = self.refiner.align(scan.map_points, scan.pose)
        return RegisteredScan(pose, scan.deskewed, scan.source, scan.map_points, cloud, hessian)

    def _sweep_searched(
        self, frame: np.ndarray, timestamps: np.ndarray, refined: RegisteredScan, sigma: float
    ) -> RegisteredScan:
        """The scan deskewed with the sweep rotation that fits KISS-ICP's map best (`best_sweep_rotation`).

        Each trial, the prediction's rotation among them, registers every TRIAL_STRIDE-th point of its source from
        `refined`'s pose (the scan as registered before the search), so that their fits compare alike. The rotation
        found, where it is not the prediction's, is registered again with every point and refined, and kept where
        it then fits the map better than `refined`: unrefined, a Mid-360-like walker's trials follow its scan
        pattern (see `GaussianMapRefiner`) and a turned rotation can fit best without being better."""
        map_fit = MapFit(self.local_map.point_cloud(), sigma)

        def trial(rotation_vector: np.ndarray) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
            motion = turned(self.last_delta, rotation_vector)
            scan = self._registered(frame, timestamps, motion, refined.pose, sigma, TRIAL_STRIDE)
            return map_fit.cost(scan.source, scan.pose), (motion, scan.pose)

        first = trial(np.zeros(3))
        best = best_sweep_rotation(first, trial)
        if best is first[1]:
            return refined
        motion, pose = best
        turned_scan = self._refined(self._registered(frame, timestamps, motion, pose, sigma))
        better = map_fit.cost(turned_scan.source, turned_scan.pose) < map_fit.cost(refined.source, refined.pose)
        return turned_scan if better else refined


class KissIcpOdometry:
    """KISS-ICP over the scans (deskewed with their per-point times when they have them). The scans of the first
    two keyframe distances are held back until the start is re-registered (`reregister_start`); later poses get
    the same correction.

    KISS-ICP deskews a scan with the motion between its last two poses, which it does not have for its first two
    scans: a drive that starts in motion would leave them, and the first keyframe's submap, bent by a sweep's
    worth of motion. The held scans are therefore deskewed again with the motion of their re-registered poses,
    registered again, and the submaps take them as deskewed then.
    """

    def __init__(self, config: SlamConfig):
        self.config = config
        self.kiss_icp = ScanOdometry(config.odometry, config.odometry_gicp)
        # The scan as the submaps take it: KISS-ICP's own voxelisation when that is fine enough.
        self._own_scan = config.keyframes.submap_voxel >= 0.5 * config.odometry.mapping.voxel_size
        self._held: list[OdometryPose] = []
        self._held_raw: list[Scan] = []  # the held scans as they came, to deskew them again
        self._correction: np.ndarray | None = None  # KISS-ICP's frame -> the re-registered start's, once known
        self._stamps: deque[float] = deque(maxlen=PERIOD_SCANS + 1)  # of the scans seen, skipped ones included
        self._registered_stamp: float | None = None
        self.unmatched: list[int] = []  # scans without a pose: none, KISS-ICP gives every scan one

    def add(self, scan: Scan) -> list[OdometryPose]:
        """Register a scan with finite points; the poses that are final now (none while the start is held)."""
        deskewed, _ = self.kiss_icp.register_frame(scan.points, scan.times, self._sweeps(scan.timestamp))
        pose = self.kiss_icp.last_pose.copy()
        stamp = scan.timestamp + (sweep_middle(scan.times) if self._deskews(scan) else 0.0)
        points = self.kiss_icp.map_points if self._own_scan else self._submap_points(deskewed)
        if self._correction is not None:
            return [(stamp, self._correction @ pose, points)]
        self._held.append((stamp, pose, points))
        self._held_raw.append(scan)
        held_poses = np.array([held[1] for held in self._held])
        if len(self._held) >= MAX_HELD_SCANS or path_length(held_poses)[-1] >= 2.0 * self.config.keyframes.distance:
            return self._release_start()
        return []

    def finish(self) -> list[OdometryPose]:
        """The poses of a start still held."""
        return self._release_start() if self._correction is None and self._held else []

    def _release_start(self) -> list[OdometryPose]:
        stamps, poses, scans = zip(*self._held)
        poses = np.asarray(poses)
        distance = self.config.keyframes.distance
        fixed = reregister_start(self.kiss_icp, poses, list(scans), distance)
        if all(self._deskews(scan) for scan in self._held_raw) and len(poses) > 1:
            scans = self._deskewed_again(fixed)
            fixed = reregister_start(self.kiss_icp, poses, scans, distance)
            scans = self._deskewed_again(fixed)
        self._correction = fixed[-1] @ np.linalg.inv(poses[-1])
        self._held, self._held_raw = [], []
        return list(zip(stamps, fixed, scans))

    def _deskewed_again(self, poses: np.ndarray) -> list[np.ndarray]:
        """The held scans deskewed with the motion between consecutive `poses` (the first with the second's), as
        the submaps take them."""
        motions = [np.linalg.inv(a) @ b for a, b in zip(poses[:-1], poses[1:])]
        preprocessor, deskew = self.kiss_icp.preprocessor, self.config.odometry.data.deskew
        deskewed = [
            deskew_to_middle(preprocessor, s.points, s.times, m, deskew)
            for s, m in zip(self._held_raw, [motions[0], *motions])
        ]
        return [self.kiss_icp.voxelize(d)[1] if self._own_scan else self._submap_points(d) for d in deskewed]

    def skip(self, stamp: float) -> None:
        """A scan at `stamp` [s] that is not registered (`Frontend.skip`): the next is predicted past it."""
        self._stamps.append(stamp)

    def _sweeps(self, stamp: float) -> int:
        """Sweeps from the scan registered last to the one at `stamp` [s]: the step between their stamps over the
        median step between the PERIOD_SCANS scans seen before (skipped ones included), rounded; 1 until three steps
        are known, and 1 where the step from the scan seen last exceeds MAX_BRIDGED_SWEEPS periods. More than 1 where
        a bag lost messages or scans were skipped."""
        steps = np.diff(self._stamps)
        previous, last = (self._stamps[-1] if self._stamps else None), self._registered_stamp
        self._stamps.append(stamp)
        self._registered_stamp = stamp
        if len(steps) < 3 or not np.median(steps) > 0.0 or last is None:
            return 1
        period = float(np.median(steps))
        if stamp - previous > (MAX_BRIDGED_SWEEPS + 0.5) * period:  # the clock jumped, or the recording paused
            return 1
        return max(1, round((stamp - last) / period))

    def _submap_points(self, deskewed: np.ndarray) -> np.ndarray:
        return voxel_downsample(deskewed, self.config.keyframes.submap_voxel)

    def _deskews(self, scan: Scan) -> bool:
        return len(scan.times) > 0 and self.config.odometry.data.deskew


@dataclass(frozen=True)
class GivenPoses:
    """Odometry from another front end (FAST-LIO2, LIO-SAM, a wheel-inertial filter): T_world_sensor (N, 4, 4)
    of the scans in order (`times` None), or at `times` (N,) [s], interpolated at each scan's stamp. Scans without
    per-point times, or with poses in order, are taken as deskewed already: each scan's points in the sensor frame
    at its pose. Timed poses deskew scans that carry per-point times (`deskew`)."""

    poses: np.ndarray
    times: np.ndarray | None = None

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
            raise ValueError(f"odometry poses must be a non-empty (N, 4, 4) array, got shape {poses.shape}")
        object.__setattr__(self, "poses", poses)
        if self.times is not None:
            times = np.asarray(self.times, dtype=np.float64).ravel()
            if len(times) != len(poses):
                raise ValueError(f"{len(times)} odometry times for {len(poses)} poses")
            if np.any(np.diff(times) <= 0.0):
                raise ValueError("odometry times must increase")
            object.__setattr__(self, "times", times)

    def at(self, index: int, stamp: float) -> np.ndarray | None:
        """The pose of the scan `index` taken at `stamp` [s]; None outside the odometry's time span.

        Raises:
            ValueError: poses in order, fewer than the scans.
        """
        if self.times is None:
            if index >= len(self.poses):
                raise ValueError(f"scan {index}: the odometry has only {len(self.poses)} poses, one per scan needed")
            return self.poses[index]
        if not self.times[0] <= stamp <= self.times[-1]:
            return None
        upper = int(np.clip(np.searchsorted(self.times, stamp), 1, len(self.times) - 1))
        around = slice(upper - 1, upper + 1)  # the two poses around `stamp`: no interpolator over all of them
        _, pose = interpolate_poses(self.times[around], self.poses[around], np.array([stamp]), max_gap=np.inf)
        return pose[0]

    def deskew(self, scan: Scan, T_world_scan: np.ndarray) -> np.ndarray:
        """The points (N, 3) of a scan with per-point times, each moved from the sensor frame at its own time
        (stamp + its time) into the sensor frame at `T_world_scan`, the pose at the scan's stamp, along the timed
        poses (interpolated; held at the first or last pose outside their span; times rounded to DESKEW_STEP).

        Raises:
            ValueError: poses in order, without times.
        """
        if self.times is None:
            raise ValueError("poses in order have no times to deskew with")
        steps, inverse = np.unique(np.round(scan.times / DESKEW_STEP).astype(np.int64), return_inverse=True)
        at = np.clip(scan.timestamp + steps * DESKEW_STEP, self.times[0], self.times[-1])
        first = max(0, min(int(np.searchsorted(self.times, at[0])) - 1, len(self.times) - 2))
        last = max(first + 2, int(np.searchsorted(self.times, at[-1])) + 1)
        _, poses = interpolate_poses(self.times[first:last], self.poses[first:last], at, max_gap=np.inf)
        relative = np.linalg.inv(T_world_scan) @ poses  # T_scan_point per time step
        rotations, translations = relative[inverse.ravel(), :3, :3], relative[inverse.ravel(), :3, 3]
        return np.einsum("nij,nj->ni", rotations, scan.points) + translations


class GivenOdometry:
    """`GivenPoses` as the front end's odometry. Scans without a pose are not used; `unmatched` lists their indices
    (in the order they were added). Poses in order are one per scan seen, skipped ones included. With `deskew`,
    timed poses deskew the scans that carry per-point times (`GivenPoses.deskew`)."""

    def __init__(self, given: GivenPoses, submap_voxel: float, deskew: bool = True):
        self.given = given
        self.submap_voxel = submap_voxel
        self.deskews = deskew and given.times is not None
        self.unmatched: list[int] = []
        self._seen = 0  # scans added or skipped
        self._added = 0

    def add(self, scan: Scan) -> list[OdometryPose]:
        pose = self.given.at(self._seen, scan.timestamp)
        self._seen += 1
        self._added += 1
        if pose is None:
            self.unmatched.append(self._added - 1)
            return []
        points = self.given.deskew(scan, pose) if self.deskews and len(scan.times) else scan.points
        return [(scan.timestamp, pose, voxel_downsample(points, self.submap_voxel))]

    def skip(self, stamp: float) -> None:
        """A scan that is not added (`Frontend.skip`): the next one's pose in order is the one after its."""
        self._seen += 1

    def finish(self) -> list[OdometryPose]:
        return []


def with_motion_prior(pose: np.ndarray, prediction: np.ndarray, hessian: np.ndarray, share: float) -> np.ndarray:
    """`pose` (T_world_sensor, registered) moved towards the constant-velocity `prediction` along the translation
    directions the scan constrains weakly; `pose` itself where it constrains every direction.

    `hessian`: the registration's Gauss-Newton Hessian at `pose` (6x6, right perturbation, [rotation,
    translation]). The translation's information with the rotation marginalised (its Schur complement) splits into
    three directions; each below `share` x the largest takes a prior of that strength (`share` x the largest) at
    the prediction, and the pose moves to the minimum of the registration's quadratic cost plus that prior (the
    rotation free; tangents at the pose and at the prediction taken as one). A narrow view down a lane of pillars
    or along a wall holds its translation across the view by 1-2 % of the largest information: there the
    registration slides a few decimetres a sweep between near-equal minima, and the prediction carries each
    slide on; along the weak direction the prior keeps the motion the sweeps before had instead."""
    if share <= 0.0:
        return pose
    rotation, translation = hessian[:3, :3], hessian[3:, 3:]
    if not np.all(np.linalg.eigvalsh(rotation) > 0.0):
        return pose
    information = translation - hessian[3:, :3] @ np.linalg.solve(rotation, hessian[:3, 3:])
    strengths, directions = np.linalg.eigh(information)
    weak = directions[:, strengths < share * strengths[-1]]
    if weak.shape[1] == 0:
        return pose
    prior = np.zeros((6, 6))
    prior[3:, 3:] = share * strengths[-1] * weak @ weak.T
    correction = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(prediction) @ pose))  # pose = prediction Exp(.)
    fused = prediction @ gtsam.Pose3.Expmap(np.linalg.solve(hessian + prior, hessian @ correction)).matrix()
    # The product's rounding would grow from scan to scan through the prediction until KISS-ICP (Sophus) refuses the
    # rotation as not orthogonal: the nearest rotation instead.
    fused[:3, :3] = gtsam.Rot3.ClosestTo(fused[:3, :3]).matrix()
    return fused


def deskew_to_middle(
    preprocessor: Preprocessor, points: np.ndarray, times: np.ndarray, motion: np.ndarray, deskew: bool
) -> np.ndarray:
    """(M, 3) the `points` (N, 3) [m] KISS-ICP's `preprocessor` keeps (within its ranges), deskewed with `motion`
    (T_start_end of the sweep, 4x4, at constant velocity) into the sensor frame at the middle of their per-point
    `times` (`sweep_middle`); as they are without times or with `deskew` off.

    KISS-ICP deskews into the frame of the sweep's last point. Where `motion` is off the sweep's own (the sweep
    before's, as predicted, while the sensor turns faster or sways), every point there moves by the error times
    its time before the end: the cloud by about half the error, and its registered pose with it. About the middle,
    the points before and after it move in opposite directions, and the registered pose keeps only the
    second-order part. On the first 400 frames of suite sequences (docs/benchmarks.md, "Deskewed to the middle of
    the sweep") each sweep's registered motion came out 1.2-6 times closer to the true one."""
    deskewed = preprocessor.preprocess(points, times, motion)
    if not (deskew and len(times)):
        return deskewed
    return transform_points(motion_power(motion, 0.5), deskewed)  # T_middle_end at constant velocity


def sweep_middle(times: np.ndarray) -> float:
    """The time [s after the stamp] that scans deskewed with per-point `times` (N,) refer to (`deskew_to_middle`):
    the middle of their first and last (KISS-ICP deskews over that span)."""
    return 0.5 * (float(times.min()) + float(times.max()))


def motion_power(motion: np.ndarray, power: float) -> np.ndarray:
    """The rigid motion (4x4) `power` times over, on SE(3) (its twist scaled): the motion of `power` sweeps at the
    constant velocity of `motion` over one, or of one sweep (`power` 1/k) over k; `motion` itself for 1."""
    if power == 1.0:
        return motion
    return gtsam.Pose3.Expmap(power * gtsam.Pose3.Logmap(gtsam.Pose3(motion))).matrix()


def path_length(poses: np.ndarray) -> np.ndarray:
    """(F,) path length [m] travelled at each of the (F, 4, 4) poses."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])


def reregister_start(odometry: KissICP, poses: np.ndarray, scans: list[np.ndarray], distance: float) -> np.ndarray:
    """The first scans' poses (F, 4, 4), re-registered: each scan of the first `distance` metres aligned, from
    the last back to the first, onto a map of the scans after them, with KISS-ICP's own registration; returned
    relative to the first scan again. `scans` are the deskewed scans at `poses`, voxelised no coarser than
    KISS-ICP voxelises them for its map.

    Starting from rest, KISS-ICP fills its map with the ground rings of near-identical scans, and the rings of
    the next scans lock onto them: where little else pins the motion along a street, the odometry stays behind
    while the vehicle speeds up, an error every later pose keeps and no loop removes (those scans move rigidly
    with the first keyframe). The scans of the next `distance` metres, taken in motion, make a map without that
    pattern.
    """
    first = int(np.searchsorted(path_length(poses), distance))  # the first scan of the map
    if first >= len(poses):
        return poses
    local_map = get_voxel_hash_map(odometry.config)
    for pose, scan in zip(poses[first:], scans[first:]):
        local_map.add_points(transform_points(pose, odometry.voxelize(scan)[1]))
    sigma = odometry.adaptive_threshold.get_threshold()
    fixed = poses.copy()
    for i in range(first - 1, -1, -1):
        guess = fixed[i + 1] @ np.linalg.inv(poses[i + 1]) @ poses[i]
        fixed[i] = odometry.registration.align_points_to_map(
            odometry.voxelize(scans[i])[0], local_map, guess, 3.0 * sigma, sigma
        )
    return np.linalg.inv(fixed[0]) @ fixed
