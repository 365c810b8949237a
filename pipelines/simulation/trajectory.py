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
    heading east (or `start` metres further along). Straight sides joined by quarter turns; each turn is a
    circular arc entered and left through clothoids (curvature linear in arc length over `transition`
    metres), as roads are built, so the yaw rate ramps up and down instead of jumping."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    corner_radius: float = 12.0  # [m]
    transition: float = 8.0  # [m] clothoid at each end of a turn (0: plain arcs, the yaw rate steps)
    start: float = 0.0  # arc length [m] from the south mid-point at which the drive starts

    def __post_init__(self) -> None:
        if not 0.0 <= self.transition <= 0.5 * np.pi * self.corner_radius:
            raise ValueError(f"a turn of radius {self.corner_radius} m cannot hold two {self.transition} m transitions")

    def _segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per segment: start (x, y, heading) (S, 3), length (S,) [m], curvature at its start (S,) [1/m]
        and curvature rate (S,) [1/m^2]."""
        r, ramp = self.corner_radius, self.transition
        rate = 1.0 / (r * ramp) if ramp > 0.0 else 0.0
        turn = [(ramp, 0.0, rate), (0.5 * np.pi * r - ramp, 1 / r, 0.0), (ramp, 1 / r, -rate)]  # (length, k0, rate)
        state = np.zeros((1, 3))
        for segment in turn:
            state = _advance(state, *(np.array([value]) for value in segment))
        extent = state[0, 0]  # a symmetric turn reaches as far along its entry as across it
        width, height = self.xmax - self.xmin, self.ymax - self.ymin
        sides = [0.5 * width - extent, height - 2 * extent, width - 2 * extent, height - 2 * extent]
        segments = [piece for side in sides for piece in [(side, 0.0, 0.0), *turn]] + [(sides[0], 0.0, 0.0)]
        lengths, k0s, rates = np.array(segments).T
        starts = np.zeros((len(lengths), 3))
        starts[0] = [0.5 * (self.xmin + self.xmax), self.ymin, 0.0]
        for k in range(1, len(lengths)):
            starts[k] = _advance(starts[k - 1 : k], lengths[k - 1 : k], k0s[k - 1 : k], rates[k - 1 : k])[0]
        return starts, lengths, k0s, rates

    @property
    def length(self) -> float:
        """Length of one lap [m]."""
        return float(self._segments()[1].sum())

    def centreline(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At arc lengths s (M,) [m] (taken modulo the lap length): positions (M, 2) [m], headings (M,)
        [rad, counter-clockwise from world x] and curvatures (M,) [1/m, positive turning left]."""
        starts, lengths, k0s, rates = self._segments()
        ends = np.cumsum(lengths)
        s = np.mod(s + self.start, ends[-1])
        k = np.minimum(np.searchsorted(ends, s, side="right"), len(lengths) - 1)
        along = s - (ends[k] - lengths[k])
        state = _advance(starts[k], along, k0s[k], rates[k])
        return state[:, :2], state[:, 2], k0s[k] + rates[k] * along


_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(16)


def _advance(start: np.ndarray, distance: np.ndarray, curvature: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """(x, y, heading) after driving `distance` [m] from `start` (M, 3) with curvature `curvature` [1/m]
    at the start, changing by `rate` [1/m^2] per metre (a clothoid; 0: an arc or a straight line). The
    heading is exact; the position is Gauss-Legendre quadrature, exact to rounding on these turns."""
    x, y, h = start.T
    u = 0.5 * distance[:, None] * (1.0 + _NODES)  # (M, 16) quadrature points along the way
    heading = h[:, None] + curvature[:, None] * u + 0.5 * rate[:, None] * u**2
    w = 0.5 * distance[:, None] * _WEIGHTS
    dx, dy = np.sum(w * np.cos(heading), axis=1), np.sum(w * np.sin(heading), axis=1)
    return np.stack([x + dx, y + dy, h + curvature * distance + 0.5 * rate * distance**2], axis=1)


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
