"""A simulated LiDAR sequence with ground truth: the world, the trajectory and the sensor put together.

Time convention (all times in seconds):
- Frame i (a `sandro_slam.Scan`) has `timestamp` = i * sweep_period (sequence time starts at 0): its sweep start.
- `times` are per point, relative to `timestamp`, in [0, sweep_period); sweeps follow each other without gap.
  They are the firing times of the sensor (`Lidar.firing_times(i)`), continuous within the sweep.
- `points` are raw, as a real driver delivers them: each point in the sensor frame at its own time
  `timestamp + times[k]`, so `poses_at(timestamp + times[k]) @ [points[k], 1]` lies on the world surface
  (up to range noise). Nothing is motion-compensated.
- `ground_truth[i]` is T_world_sensor at `timestamp[i]`; `poses_at(t)` gives it at any time.

KISS-ICP 1.3 (`KissICP.register_frame(points, times)`, C++ `Preprocessor::Preprocess`) rescales each
frame's timestamps to s in [0, 1] by their own min and max and moves point k by exp((s_k - 1) * log(delta)),
delta being the motion between its last two pose estimates. So pass `frame.points, frame.times` unchanged
(relative or absolute stamps work alike; an empty array turns deskewing off). The points then end up in
the sensor frame at the frame's LATEST point, and the pose KISS-ICP returns is T_world_sensor at
`timestamp + times.max()` (= timestamp + sweep_period * (1 - 1 / columns) for a `SpinningLidar`), not at
`timestamp`: compare it with `poses_at(timestamp + times.max())`. Its first frame is not deskewed (no motion
estimate yet); `simulate_sequence` therefore starts from rest.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pipelines.simulation.sensor import Lidar, SpinningLidar
from pipelines.simulation.trajectory import PolylineRoute, Route, Trajectory, random_sway, random_wobble
from pipelines.simulation.world import CityLayout, World, build_city
from sandro_core.geometry import transform_points
from sandro_slam.scan import Scan


class SimulatedSequence:
    """Frames generated on demand (bounded memory) and their ground truth.

    Attributes:
        world, trajectory, lidar: what the frames are simulated from.
        timestamps: (M,) frame stamps [s].
        ground_truth: (M, 4, 4) T_world_sensor at `timestamps`.
    """

    def __init__(
        self,
        world: World,
        trajectory: Trajectory,
        lidar: Lidar,
        num_frames: int,
        noise_sigma: float,
        seed: int,
    ) -> None:
        self.world = world
        self.trajectory = trajectory
        self.lidar = lidar
        self.noise_sigma = noise_sigma
        self.seed = seed
        self.timestamps = np.arange(num_frames) * lidar.sweep_period
        self.ground_truth = trajectory.poses(self.timestamps)
        self._scene = world.raycasting_scene()

    def __len__(self) -> int:
        return len(self.timestamps)

    def poses_at(self, times: np.ndarray | float) -> np.ndarray:
        """Ground truth T_world_sensor (M, 4, 4) at sequence times (M,) [s]."""
        return self.trajectory.poses(times)

    def frame(self, index: int) -> Scan:
        """Frame `index`; the same for a given seed whatever the order frames are asked for in."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} out of range [0, {len(self)})")
        timestamp = float(self.timestamps[index])
        rng = np.random.default_rng([self.seed, 2, index])  # streams: city seed, wobble [seed, 1], sway [seed, 3]
        poses = self.poses_at(timestamp + self.lidar.firing_times(index))
        points, times = self.lidar.scan(self._scene, poses, index, self.noise_sigma, rng)
        return Scan(timestamp, points, times)

    def frames(self) -> Iterator[Scan]:
        """All frames in order, one at a time."""
        for index in range(len(self)):
            yield self.frame(index)

    def deskewed(self, index: int) -> tuple[Scan, np.ndarray]:
        """Frame `index` deskewed with the true motion: `deskew(frame(index))`."""
        return self.deskew(self.frame(index))

    def deskew(self, frame: Scan) -> tuple[Scan, np.ndarray]:
        """A frame of this sequence deskewed with the true motion, as a LiDAR-inertial front end delivers it: the
        scan stamped at its latest point, every point in the sensor frame at that time, no per-point times; and the
        true T_world_sensor then."""
        end = frame.timestamp + float(frame.times.max())
        firings, firing_of_point = np.unique(frame.times, return_inverse=True)  # points fire in groups
        per_point = self.poses_at(frame.timestamp + firings)[firing_of_point]
        world = np.einsum("nij,nj->ni", per_point[:, :3, :3], frame.points) + per_point[:, :3, 3]
        T_world_end = self.poses_at(end)[0]
        return Scan(end, transform_points(np.linalg.inv(T_world_end), world), np.empty(0)), T_world_end


def simulate_sequence(
    seed: int = 0,
    laps: int = 2,
    frames: int | None = None,
    spacing: float = 1.0,
    noise_sigma: float = 0.02,
    lane_offset: float = 1.5,
    wobble_deg: float = 0.3,
    layout: CityLayout = CityLayout(),
    lidar: Lidar = SpinningLidar(),
    loop: tuple[float, float, float, float] | None = None,
    start_distance: float = 0.0,
) -> SimulatedSequence:
    """A drive of `laps` laps (about 400 m each) around the two central blocks of a seeded city.

    Args:
        seed: seeds the city, the wobble and the range noise; the same seed gives identical frames.
        laps: number of laps; from lap 2 on the sensor drives `lane_offset` [m] to the left.
        frames: at most this many frames (None: all laps).
        spacing: distance between consecutive frame stamps along the route at cruise speed [m]; cruise
            speed = spacing / lidar.sweep_period (10 m/s at the defaults), reached from rest in 2 s.
        noise_sigma: range noise standard deviation [m].
        wobble_deg: roll and pitch wobble amplitude [deg] (0: none).
        layout: street grid of the city.
        lidar: the sensor model.
        loop: (xmin, ymin, xmax, ymax) street centrelines [m] of the loop driven (None: `layout.loop`).
        start_distance: the drive starts this far [m] along the loop from its south mid-point.
    """
    route = Route(*(layout.loop if loop is None else loop), start=start_distance)
    return make_sequence(
        build_city(seed, layout), route, lidar, speed=spacing / lidar.sweep_period, distance=laps * route.length,
        lane_offset=lane_offset, wobble_deg=wobble_deg, noise_sigma=noise_sigma, seed=seed, max_frames=frames,
    )  # fmt: skip


def make_sequence(
    world: World,
    route: Route | PolylineRoute,
    lidar: Lidar = SpinningLidar(),
    speed: float = 10.0,
    distance: float | None = None,
    accel_time: float = 2.0,
    lane_offset: float = 0.0,
    wobble_deg: float = 0.0,
    sway: tuple[float, float, float] = (0.0, 0.0, 0.0),
    mount_pitch_deg: float = 0.0,
    sensor_height: float = 1.8,
    noise_sigma: float = 0.02,
    seed: int = 0,
    max_frames: int | None = None,
) -> SimulatedSequence:
    """Any sensor carried along any route through any world: the general form of `simulate_sequence`.

    Args:
        world: what the sensor sees.
        route: the centreline followed (closed: laps; open: from its first waypoint to its last).
        lidar: the sensor model (see `sensor.PRESETS`).
        speed: cruise speed along the route [m/s].
        distance: distance to drive [m], which sets the number of frames (None: one lap, or the whole open
            route).
        accel_time: time from rest to `speed` [s] (0: in motion from the first frame on).
        lane_offset: lateral offset from lap 2 on [m], positive to the left (closed routes only).
        wobble_deg: roll and pitch wobble amplitude [deg] at cruise speed (0: none).
        sway: walking sway amplitudes at cruise speed: vertical bob [m], lateral sway [m], yaw [deg] (see
            `random_sway`; zeros: none).
        mount_pitch_deg: fixed pitch of the sensor [deg], positive looking down.
        sensor_height: height of the sensor above the ground [m] (before the bob).
        noise_sigma: range noise standard deviation [m].
        seed: seeds the wobble, the sway and the range noise; the same arguments give identical frames.
        max_frames: at most this many frames (None: as many as `distance` takes).
    """
    trajectory = Trajectory(
        route=route,
        speed=speed,
        accel_time=accel_time,
        sensor_height=sensor_height,
        lane_offset=lane_offset,
        wobble=random_wobble(np.random.default_rng([seed, 1]), wobble_deg),
        sway=random_sway(np.random.default_rng([seed, 3]), *sway),
        mount_pitch_deg=mount_pitch_deg,
    )
    num_frames = int(trajectory.time_at(route.length if distance is None else distance) / lidar.sweep_period)
    if max_frames is not None:
        num_frames = min(num_frames, max_frames)
    return SimulatedSequence(world, trajectory, lidar, num_frames, noise_sigma, seed)
