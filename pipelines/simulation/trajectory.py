"""Ground-truth sensor trajectory: laps of a rounded-rectangle street loop at constant speed.

`Route` is the loop's centreline as a function of arc length; `Trajectory` drives it in continuous time
and gives T_world_sensor (4x4, maps sensor-frame points into the world frame) at any time [s].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Route:
    """A counter-clockwise rounded rectangle in the ground plane, starting mid-way along its south side,
    heading east (or `start` metres further along). Built from straight segments and quarter-circle arcs."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    corner_radius: float = 12.0  # [m]
    start: float = 0.0  # arc length [m] from the south mid-point at which the drive starts

    def _segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per segment: start (x, y, heading) (S, 3), length (S,) [m], curvature (S,) [1/m]."""
        r = self.corner_radius
        width, height = self.xmax - self.xmin, self.ymax - self.ymin
        arc = 0.5 * np.pi * r
        half = 0.5 * width - r
        lengths = np.array([half, arc, height - 2 * r, arc, width - 2 * r, arc, height - 2 * r, arc, half])
        curvatures = np.array([0.0, 1 / r] * 4 + [0.0])
        starts = np.zeros((len(lengths), 3))
        starts[0] = [0.5 * (self.xmin + self.xmax), self.ymin, 0.0]
        for k in range(1, len(lengths)):
            starts[k] = _advance(starts[k - 1 : k], lengths[k - 1 : k], curvatures[k - 1 : k])[0]
        return starts, lengths, curvatures

    @property
    def length(self) -> float:
        """Length of one lap [m]."""
        return float(self._segments()[1].sum())

    def centreline(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At arc lengths s (M,) [m] (taken modulo the lap length): positions (M, 2) [m], headings (M,)
        [rad, counter-clockwise from world x] and curvatures (M,) [1/m, positive turning left]."""
        starts, lengths, curvatures = self._segments()
        ends = np.cumsum(lengths)
        s = np.mod(s + self.start, ends[-1])
        k = np.minimum(np.searchsorted(ends, s, side="right"), len(lengths) - 1)
        state = _advance(starts[k], s - (ends[k] - lengths[k]), curvatures[k])
        return state[:, :2], state[:, 2], curvatures[k]


def _advance(start: np.ndarray, distance: np.ndarray, curvature: np.ndarray) -> np.ndarray:
    """(x, y, heading) after driving `distance` [m] at constant `curvature` [1/m] from `start` (M, 3)."""
    x, y, h = start.T
    turn = curvature * distance
    straight = np.abs(curvature) < 1e-12
    k = np.where(straight, 1.0, curvature)
    dx = np.where(straight, distance * np.cos(h), (np.sin(h + turn) - np.sin(h)) / k)
    dy = np.where(straight, distance * np.sin(h), (np.cos(h) - np.cos(h + turn)) / k)
    return np.stack([x + dx, y + dy, h + turn], axis=1)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Driving `route` from rest at time 0: constant acceleration to `speed` over `accel_time`, then
    constant speed; a lane change to `lane_offset` (left positive) at the start of lap 2, kept for later
    laps; a small sinusoidal roll/pitch wobble whose amplitude grows with the speed."""

    route: Route
    speed: float  # cruise speed along the centreline [m/s]
    accel_time: float = 2.0  # [s] from rest to `speed`
    sensor_height: float = 1.8  # [m] above the ground
    lane_offset: float = 1.5  # lateral offset from lap 2 on [m], positive to the left of travel
    lane_change_length: float = 30.0  # distance over which the offset is reached [m]
    # rows roll, pitch; columns amplitude at cruise speed [rad], frequency [Hz], phase [rad]
    wobble: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))

    def _speed_ratio(self, t: np.ndarray) -> np.ndarray:
        """Speed over cruise speed at times t [s]: 0 before time 0, rising linearly to 1 at accel_time."""
        if self.accel_time == 0.0:
            return (t >= 0.0).astype(np.float64)
        return np.clip(t / self.accel_time, 0.0, 1.0)

    def distance(self, times: np.ndarray) -> np.ndarray:
        """Distance driven along the centreline [m] at times [s]."""
        t = np.maximum(times, 0.0)
        ramp = np.minimum(t, self.accel_time)
        return self.speed * (0.5 * ramp * self._speed_ratio(ramp) + (t - ramp))

    def time_at(self, distance: float) -> float:
        """Time [s] at which `distance` [m] has been driven (distance >= speed * accel_time / 2)."""
        return distance / self.speed + 0.5 * self.accel_time

    def _offset(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lateral offset [m] and its derivative along the route [m/m] at driven distance s (M,) [m]."""
        u = np.clip((s - self.route.length) / self.lane_change_length, 0.0, 1.0)
        d = 0.5 * self.lane_offset * (1.0 - np.cos(np.pi * u))
        inside = (u > 0.0) & (u < 1.0)
        slope = 0.5 * np.pi * self.lane_offset * np.sin(np.pi * u) / self.lane_change_length
        return d, np.where(inside, slope, 0.0)

    def poses(self, times: np.ndarray | float) -> np.ndarray:
        """T_world_sensor (M, 4, 4) at times (M,) [s], standing at the start before time 0.

        Sensor frame x forward, y left, z up; yaw follows the driven path, roll and pitch are the wobble.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        s = self.distance(t)
        xy, heading, curvature = self.route.centreline(s)
        d, dd = self._offset(s)
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
        yaw = heading + np.arctan2(dd, 1.0 - d * curvature)
        amplitude, frequency, phase = self.wobble.T
        angle = 2 * np.pi * frequency[:, None] * t + phase[:, None]
        roll, pitch = amplitude[:, None] * self._speed_ratio(t) * np.sin(angle)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
        T[:, :2, 3] = xy + d[:, None] * normal
        T[:, 2, 3] = self.sensor_height
        return T


def random_wobble(rng: np.random.Generator, amplitude_deg: float) -> np.ndarray:
    """Roll and pitch wobble for `Trajectory.wobble`: amplitude `amplitude_deg` [deg], frequencies 0.3-1.2
    Hz and phases drawn from `rng`."""
    amplitude = np.full(2, np.deg2rad(amplitude_deg))
    return np.stack([amplitude, rng.uniform(0.3, 1.2, size=2), rng.uniform(0.0, 2 * np.pi, size=2)], axis=1)
