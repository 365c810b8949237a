"""Ground-truth sensor trajectory: a route driven (or walked) at constant speed.

`Route` (a rounded-rectangle street loop) and `PolylineRoute` (waypoints joined by rounded corners) are
centrelines as functions of arc length; `Trajectory` drives one in continuous time and gives T_world_sensor
(4x4, maps sensor-frame points into the world frame) at any time [s].
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
        return _follow(self._segments(), s + self.start, closed=True)


@dataclass(frozen=True, eq=False)
class PolylineRoute:
    """Waypoints joined by straight segments, every corner rounded: a circular arc of `corner_radius` tangent
    to both segments, entered and left through clothoids of `transition` metres as in `Route` (0: plain arcs,
    the yaw rate steps). A corner turning by less than transition / corner_radius [rad] is two clothoids
    meeting at a curvature below 1 / corner_radius. Corners turning by less than 1e-9 rad are left straight.

    Open: from the first waypoint to the last, rounding the interior corners; arc lengths past either end
    are clamped (the route stands still there). Closed: the corner at the first waypoint is rounded too, and
    the route starts midway along the straight part of its first segment (waypoint 0 to 1) and wraps modulo
    its length; a last waypoint equal to the first is dropped. Either way it starts `start` metres further on.
    """

    waypoints: np.ndarray  # (K, 2) [m], world x, y
    corner_radius: float  # [m]
    closed: bool
    transition: float = 0.0  # [m] clothoid at each end of a turn
    start: float = 0.0  # [m] arc length from the route's start point at which the drive starts

    _segments: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        waypoints = np.array(self.waypoints, dtype=np.float64)
        if self.closed and len(waypoints) > 1 and np.array_equal(waypoints[0], waypoints[-1]):
            waypoints = waypoints[:-1]
        object.__setattr__(self, "waypoints", waypoints)
        object.__setattr__(self, "_segments", self._build())

    def _build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As `Route._segments`: per segment start (x, y, heading) (S, 3), length (S,) [m], curvature at its
        start (S,) [1/m] and curvature rate (S,) [1/m^2]; the first segment starts at the route's start point."""
        points = self.waypoints
        if points.ndim != 2 or points.shape[1] != 2 or len(points) < (3 if self.closed else 2):
            raise ValueError(f"waypoints must be (K, 2) with K >= {3 if self.closed else 2}, got {points.shape}")
        edges = (np.roll(points, -1, axis=0) - points) if self.closed else np.diff(points, axis=0)
        sides = np.linalg.norm(edges, axis=1)
        if np.any(sides == 0.0):
            raise ValueError(f"waypoints {np.flatnonzero(sides == 0.0)[0]} and the next coincide")
        directions = np.arctan2(edges[:, 1], edges[:, 0])
        # corners by their waypoints, in driving order (the closed route starts on the first segment)
        corners = np.roll(np.arange(len(points)), -1) if self.closed else np.arange(1, len(points) - 1)
        turns = np.angle(np.exp(1j * (directions[corners % len(edges)] - directions[corners - 1])))
        turn_pieces, tangents = [], np.zeros(len(corners))  # [m] from each corner's waypoint to its ends
        for k, (turn, waypoint) in enumerate(zip(turns, corners)):
            pieces, tangents[k] = self._corner(turn, waypoint)
            turn_pieces.append(pieces)
        cut = np.zeros((len(edges), 2))  # [m] taken by the corners at each edge's start and end
        cut[corners % len(edges), 0] = tangents
        cut[corners - 1, 1] = tangents
        straight = sides - cut.sum(axis=1)
        if np.any(straight < -1e-9 * sides):
            k = int(np.argmin(straight / sides))
            raise ValueError(
                f"the corners at waypoints {k} and {(k + 1) % len(points)} need {cut[k].sum():.2f} m of their "
                f"{sides[k]:.2f} m segment (corner_radius {self.corner_radius} m, transition {self.transition} m)"
            )
        straight = np.maximum(straight, 0.0)
        first = 0.5 * straight[0] if self.closed else straight[0]
        segments = [(first, 0.0, 0.0)]
        for corner, pieces in zip(corners, turn_pieces):
            segments += [*pieces, (straight[corner % len(edges)], 0.0, 0.0)]
        if self.closed:
            segments[-1] = (straight[0] - first, 0.0, 0.0)
        lengths, k0s, rates = np.array(segments).reshape(-1, 3).T
        start_point = points[0] + edges[0] / sides[0] * (cut[0, 0] + (first if self.closed else 0.0))
        starts = np.zeros((len(lengths), 3))
        starts[0] = [*start_point, directions[0]]
        for k in range(1, len(lengths)):
            starts[k] = _advance(starts[k - 1 : k], lengths[k - 1 : k], k0s[k - 1 : k], rates[k - 1 : k])[0]
        return starts, lengths, k0s, rates

    def _corner(self, turn: float, waypoint: int) -> tuple[list[tuple[float, float, float]], float]:
        """The pieces (length [m], curvature at start [1/m], curvature rate [1/m^2]) of the corner turning by
        `turn` [rad, positive left] at `waypoint`, and the distance [m] from the waypoint at which it starts
        and ends on its two segments."""
        if abs(turn) > np.deg2rad(170.0):
            raise ValueError(f"the corner at waypoint {waypoint} turns {np.rad2deg(abs(turn)):.1f} deg, more than 170")
        if abs(turn) < 1e-9:
            return [], 0.0
        r, ramp = self.corner_radius, self.transition
        curvature = np.sign(turn) * (min(1.0 / r, abs(turn) / ramp) if ramp > 0.0 else 1.0 / r)
        rate = curvature / ramp if ramp > 0.0 else 0.0
        arc = (abs(turn) - abs(curvature) * ramp) / abs(curvature)
        pieces = [(ramp, 0.0, rate), (arc, curvature, 0.0), (ramp, curvature, -rate)]
        state = np.zeros((1, 3))
        for piece in pieces:
            state = _advance(state, *(np.array([value]) for value in piece))
        x, y = state[0, :2]  # the end of a symmetric turn started at the origin heading along x
        return pieces, float(x - y / np.tan(turn))

    @property
    def length(self) -> float:
        """Length of the route (of one lap when closed) [m]."""
        return float(self._segments[1].sum())

    def centreline(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At arc lengths s (M,) [m] from the start (taken modulo the length when closed, clamped to the route
        when open): positions (M, 2) [m], headings (M,) [rad, counter-clockwise from world x] and curvatures
        (M,) [1/m, positive turning left]."""
        return _follow(self._segments, np.asarray(s, dtype=np.float64) + self.start, self.closed)


def _follow(
    segments: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], s: np.ndarray, closed: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (M, 2) [m], headings (M,) [rad] and curvatures (M,) [1/m] at arc lengths s (M,) [m] along
    `segments` (starts, lengths, curvatures at start, curvature rates; see `Route`), taken modulo their total
    length when `closed`, else clamped to [0, total length]."""
    starts, lengths, k0s, rates = segments
    ends = np.cumsum(lengths)
    s = np.mod(s, ends[-1]) if closed else np.clip(s, 0.0, ends[-1])
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
    """Driving `route` from time 0: constant acceleration from rest to `speed` over `accel_time` (0: at full
    speed from time 0 on), then constant speed; a lane change to `lane_offset` (left positive) at the start of
    lap 2 (one route length driven; never on an open route, which then stands at its end), kept for later
    laps; a small sinusoidal roll/pitch wobble and a walking sway, both growing with the speed; the sensor
    mounted `mount_pitch_deg` nose down."""

    route: Route | PolylineRoute
    speed: float  # cruise speed along the centreline [m/s]
    accel_time: float = 2.0  # [s] from rest to `speed`
    sensor_height: float = 1.8  # [m] above the ground
    lane_offset: float = 1.5  # lateral offset from lap 2 on [m], positive to the left of travel
    lane_change_length: float = 30.0  # distance over which the offset is reached [m]
    # rows roll, pitch; columns amplitude at cruise speed [rad], frequency [Hz], phase [rad]
    wobble: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    # rows vertical bob [m], lateral sway [m] (left positive), yaw [rad]; columns amplitude at cruise speed,
    # frequency [Hz], phase [rad] (see `random_sway`)
    sway: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    mount_pitch_deg: float = 0.0  # fixed pitch of the sensor on its carrier [deg], positive tilting x down

    def _speed_ratio(self, t: np.ndarray) -> np.ndarray:
        """Speed over cruise speed at times t [s]: 0 before time 0, rising linearly to 1 at accel_time."""
        if self.accel_time == 0.0:
            return (t >= 0.0).astype(np.float64)
        return np.clip(t / self.accel_time, 0.0, 1.0)

    def _oscillations(self, table: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(R, M) sinusoids of `table` rows (amplitude at cruise speed, frequency [Hz], phase [rad]) at times t
        (M,) [s], scaled by the speed ratio."""
        amplitude, frequency, phase = table.T
        angle = 2 * np.pi * frequency[:, None] * t + phase[:, None]
        return amplitude[:, None] * self._speed_ratio(t) * np.sin(angle)

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

        Sensor frame x forward, y left, z up; yaw follows the driven path plus the yaw sway, roll and pitch
        are the wobble, then the mount pitch; the bob moves the sensor up, the lateral sway to the left.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        s = self.distance(t)
        xy, heading, curvature = self.route.centreline(s)
        d, dd = self._offset(s)
        bob, lateral, yaw_sway = self._oscillations(self.sway, t)
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
        yaw = heading + np.arctan2(dd, 1.0 - d * curvature) + yaw_sway
        roll, pitch = self._oscillations(self.wobble, t)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        body = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
        T[:, :3, :3] = body @ Rotation.from_euler("Y", np.deg2rad(self.mount_pitch_deg)).as_matrix()
        T[:, :2, 3] = xy + (d + lateral)[:, None] * normal
        T[:, 2, 3] = self.sensor_height + bob
        return T


def random_wobble(rng: np.random.Generator, amplitude_deg: float) -> np.ndarray:
    """Roll and pitch wobble for `Trajectory.wobble`: amplitude `amplitude_deg` [deg], frequencies 0.3-1.2
    Hz and phases drawn from `rng`."""
    amplitude = np.full(2, np.deg2rad(amplitude_deg))
    return np.stack([amplitude, rng.uniform(0.3, 1.2, size=2), rng.uniform(0.0, 2 * np.pi, size=2)], axis=1)


def random_sway(rng: np.random.Generator, bob: float, lateral: float, yaw_deg: float) -> np.ndarray:
    """Walking sway for `Trajectory.sway`: a vertical bob of amplitude `bob` [m] at the step frequency (drawn
    in 1.8-2.0 Hz), a lateral sway of `lateral` [m] and a yaw oscillation of `yaw_deg` [deg] at half of it
    (one per stride), phases drawn from `rng`."""
    step = rng.uniform(1.8, 2.0)
    amplitude = np.array([bob, lateral, np.deg2rad(yaw_deg)])
    return np.stack([amplitude, [step, 0.5 * step, 0.5 * step], rng.uniform(0.0, 2 * np.pi, size=3)], axis=1)
