"""Sensor presets (spinning and non-repetitive), polyline routes, starts in motion, walking sway and mount pitch."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipelines.simulation import (
    PRESETS,
    CityLayout,
    PolylineRoute,
    Route,
    SimulatedSequence,
    Trajectory,
    World,
    make_sequence,
    simulate_sequence,
)
from pipelines.simulation.trajectory import random_sway

# per preset: rays per sweep, and the field of view as (elevation min, max) [deg] or a cone half-angle [deg]
FIELDS_OF_VIEW = {
    "vlp16": (16 * 1800, (-15.0, 15.0)),
    "spinning32": (32 * 900, (-25.0, 15.0)),
    "os128": (128 * 1024, (-22.5, 22.5)),
    "avia": (24_000, 35.2),
    "mid360": (20_000, (-7.0, 52.0)),
}


@pytest.fixture(scope="module")
def city() -> World:
    return simulate_sequence(frames=1).world


def to_world(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by per-point (N, 4, 4) or shared (4, 4) poses."""
    if poses.ndim == 2:
        return points @ poses[:3, :3].T + poses[:3, 3]
    return np.einsum("nij,nj->ni", poses[:, :3, :3], points) + poses[:, :3, 3]


def spherical(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation [deg] of (N, 3) directions."""
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return np.rad2deg(np.arctan2(unit[:, 1], unit[:, 0])), np.rad2deg(np.arcsin(unit[:, 2]))


def coverage(directions: np.ndarray, field_of_view, cell: float = 1.0) -> float:
    """Share of the cells (`cell` degrees wide) of a field of view holding a direction: an azimuth-elevation
    grid for an elevation band, a grid over the disk of deflections (1 deg inside its rim) for a cone."""
    if isinstance(field_of_view, tuple):
        azimuth, elevation = spherical(directions)
        edges = np.arange(-180.0, 180.0 + 1e-9, cell), np.arange(field_of_view[0], field_of_view[1] + 1e-9, cell)
        return float(np.mean(np.histogram2d(azimuth, elevation, bins=edges)[0] > 0))
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    tilt = np.rad2deg(np.arccos(np.clip(unit[:, 0], -1.0, 1.0)))
    u, v = tilt * np.cos(np.arctan2(unit[:, 2], unit[:, 1])), tilt * np.sin(np.arctan2(unit[:, 2], unit[:, 1]))
    radius = field_of_view - 1.0
    edges = np.arange(-radius, radius + 1e-9, cell)
    centres = 0.5 * (edges[1:] + edges[:-1])
    inside = np.hypot(*np.meshgrid(centres, centres, indexing="ij")) < radius - cell
    return float(np.mean(np.histogram2d(u, v, bins=[edges, edges])[0][inside] > 0))


@pytest.mark.parametrize("name", FIELDS_OF_VIEW)
def test_every_ray_lies_in_the_field_of_view_and_the_sweep_is_ordered_in_time(name):
    """Inside a closed box every ray returns: the points are the whole pattern."""
    lidar = PRESETS[name]
    rays, field_of_view = FIELDS_OF_VIEW[name]
    scene = World(boxes=np.array([[-30.0, -30.0, -20.0, 30.0, 30.0, 20.0]]), ground=(900.0, 900.0, 901.0, 901.0))
    times = lidar.firing_times(3)
    poses = np.broadcast_to(np.eye(4), (len(times), 4, 4))
    points, point_times = lidar.scan(scene.raycasting_scene(), poses, 3)
    assert points.shape == (rays, 3) and points.dtype == np.float64 and point_times.shape == (rays,)
    assert np.all(np.diff(point_times) >= 0.0) and point_times[0] >= 0.0 and point_times[-1] < lidar.sweep_period
    np.testing.assert_array_equal(np.unique(point_times), times)
    azimuth, elevation = spherical(points)
    if isinstance(field_of_view, tuple):
        assert field_of_view[0] - 1e-9 <= elevation.min() and elevation.max() <= field_of_view[1] + 1e-9
        assert elevation.min() < field_of_view[0] + 0.5 and elevation.max() > field_of_view[1] - 0.5
        assert np.ptp(azimuth) > 359.0
    else:
        tilt = np.rad2deg(np.arccos(points[:, 0] / np.linalg.norm(points, axis=1)))
        assert field_of_view - 0.5 < tilt.max() <= field_of_view


@pytest.mark.parametrize("name", ["avia", "mid360"])
def test_non_repetitive_patterns_change_every_sweep_and_fill_the_field_of_view_in_a_second(name):
    lidar = PRESETS[name]
    field_of_view = FIELDS_OF_VIEW[name][1]
    sweeps = [lidar.ray_directions(k).reshape(-1, 3) for k in range(round(1.0 / lidar.sweep_period))]
    gap = np.rad2deg(cKDTree(sweeps[0]).query(sweeps[1])[0])  # [deg] from each ray of sweep 1 to sweep 0's
    assert np.median(gap) > 0.05
    one, all_ = coverage(sweeps[0], field_of_view), coverage(np.concatenate(sweeps), field_of_view)
    assert one < 0.9 and all_ > 0.99


@pytest.mark.parametrize("name", FIELDS_OF_VIEW)
def test_points_lie_on_the_world_at_their_own_time_and_deskew(name, city):
    """A handheld-like carrier turning a corner: wobble, walking sway and a tilted mount."""
    sequence = make_sequence(
        city, Route(*CityLayout().loop), PRESETS[name], speed=8.0, distance=110.0, accel_time=0.0,
        wobble_deg=0.5, sway=(0.04, 0.05, 3.0), mount_pitch_deg=10.0, noise_sigma=0.0, seed=1,
    )  # fmt: skip
    start, end = sequence.ground_truth, sequence.poses_at(sequence.timestamps + sequence.lidar.sweep_period)
    yaw_start, yaw_end = np.arctan2(start[:, 1, 0], start[:, 0, 0]), np.arctan2(end[:, 1, 0], end[:, 0, 0])
    turn = np.abs(np.angle(np.exp(1j * (yaw_end - yaw_start))))  # [rad] during each sweep
    index = int(np.argmax(turn))
    assert np.rad2deg(turn[index]) > 3.0
    frame = sequence.frame(index)
    assert len(frame.points) > 5000
    own = to_world(sequence.poses_at(frame.timestamp + frame.times), frame.points)
    assert city.distance(own).max() < 2e-3
    stamp_only = city.distance(to_world(sequence.ground_truth[index], frame.points))
    assert np.percentile(stamp_only, 90) > 0.05
    deskewed, T_world_end = sequence.deskew(frame)
    assert deskewed.timestamp == frame.timestamp + frame.times.max()
    assert city.distance(to_world(T_world_end, deskewed.points)).max() < 2e-3


def test_default_sequence_reproduces_the_frames_it_always_gave():
    """simulate_sequence() as before sensors became pluggable (point counts exact; sums to rounding of the
    float32 ray caster), which the demo's cached data depends on."""
    sequence = simulate_sequence()
    expected = {
        0: (26458, [297662.014209, 285282.310245, 59623.418229]),
        5: (26471, [299069.145394, 285877.090342, 59956.169066]),
        300: (27500, [251434.163144, 202368.759781, 50330.659416]),
    }
    for index, (count, sums) in expected.items():
        frame = sequence.frame(index)
        assert len(frame.points) == count
        np.testing.assert_allclose(np.abs(frame.points).sum(axis=0), sums, rtol=1e-8)
        np.testing.assert_array_equal(np.unique(frame.times), sequence.lidar.column_times)
    np.testing.assert_allclose(sequence.ground_truth[300, :3, 3], [0.0, 43.309228, 1.8], atol=1e-6)


SQUARE_ISH = [[0.0, 0.0], [60.0, 0.0], [80.0, 40.0], [20.0, 70.0], [-10.0, 30.0]]


def test_closed_polyline_route_is_straights_and_arcs_with_continuous_heading():
    r = 8.0
    route = PolylineRoute(SQUARE_ISH, corner_radius=r, closed=True)
    points = np.array(SQUARE_ISH)
    edges = np.roll(points, -1, axis=0) - points
    directions = np.arctan2(edges[:, 1], edges[:, 0])
    turns = np.angle(np.exp(1j * (directions - np.roll(directions, 1))))  # at each waypoint, all to the left
    tangents = r * np.tan(turns / 2)  # from each waypoint to where its arc starts and ends
    assert route.length == pytest.approx(np.linalg.norm(edges, axis=1).sum() - 2 * tangents.sum() + r * turns.sum())
    step = 0.01
    s = np.arange(0.0, route.length, step)
    xy, heading, curvature = route.centreline(s)
    np.testing.assert_allclose(xy[0], [0.5 * (tangents[0] + 60.0 - tangents[1]), 0.0], atol=1e-9)  # mid-straight
    assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= step + 1e-9
    dh = np.angle(np.exp(1j * np.diff(heading)))
    assert np.abs(dh).max() <= step / r + 1e-9
    assert np.unwrap(heading)[-1] - heading[0] == pytest.approx(2 * np.pi, abs=1e-2)
    on_arc = curvature != 0.0
    np.testing.assert_allclose(curvature[on_arc], 1.0 / r)  # counter-clockwise: every turn to the left
    assert on_arc.mean() == pytest.approx(2 * np.pi * r / route.length, abs=2 * step * len(points) / route.length)
    (xy0, h0, k0), (xy3, h3, k3) = route.centreline(s[:900:9]), route.centreline(s[:900:9] + 3 * route.length)
    np.testing.assert_allclose(xy3, xy0, atol=1e-9)  # laps wrap
    np.testing.assert_allclose(np.angle(np.exp(1j * (h3 - h0))), 0.0, atol=1e-9)
    np.testing.assert_array_equal(k3, k0)
    repeated = PolylineRoute([*SQUARE_ISH, SQUARE_ISH[0]], corner_radius=r, closed=True)  # the same loop
    np.testing.assert_array_equal(repeated.centreline(s[:50])[0], xy[:50])
    moved = PolylineRoute(SQUARE_ISH, corner_radius=r, closed=True, start=25.0)
    np.testing.assert_allclose(moved.centreline(s[:50])[0], route.centreline(s[:50] + 25.0)[0], atol=1e-9)


def test_polyline_rectangle_matches_the_rounded_rectangle_route():
    """With clothoid transitions too: the same corners, the same start, the same lap."""
    s = np.linspace(-20.0, 900.0, 5001)
    rectangle = PolylineRoute([[0.0, 0.0], [140.0, 0.0], [140.0, 70.0], [0.0, 70.0]], 12.0, closed=True, transition=8.0)
    for a, b in zip(rectangle.centreline(s), Route(0.0, 0.0, 140.0, 70.0).centreline(s)):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_open_polyline_route_runs_from_first_to_last_waypoint_and_clamps():
    waypoints = [[0.0, 0.0], [50.0, 0.0], [50.0, 40.0], [90.0, 80.0]]
    route = PolylineRoute(waypoints, corner_radius=10.0, closed=False)
    quarter, eighth = 10.0 * np.pi / 2, 10.0 * np.pi / 4
    straights = 50.0 + 40.0 + np.hypot(40.0, 40.0) - 2 * 10.0 - 2 * 10.0 * np.tan(np.pi / 8)
    assert route.length == pytest.approx(straights + quarter + eighth)
    xy, heading, curvature = route.centreline(np.array([-5.0, 0.0, route.length, route.length + 10.0]))
    np.testing.assert_allclose(xy, [[0.0, 0.0], [0.0, 0.0], [90.0, 80.0], [90.0, 80.0]], atol=1e-9)
    np.testing.assert_allclose(heading, [0.0, 0.0, np.pi / 4, np.pi / 4], atol=1e-12)
    trajectory = Trajectory(route, speed=2.0, accel_time=0.0, lane_offset=0.0)
    end = trajectory.poses([trajectory.time_at(route.length), 1e3])
    np.testing.assert_allclose(end[:, :2, 3], [[90.0, 80.0], [90.0, 80.0]], atol=1e-9)  # stands at the end


def test_gentle_corners_with_transitions_peak_below_the_corner_curvature():
    route = PolylineRoute([[0.0, 0.0], [100.0, 0.0], [200.0, 10.0]], corner_radius=12.0, closed=False, transition=8.0)
    xy, heading, curvature = route.centreline(np.linspace(0.0, route.length, 20001))
    assert 0.0 < curvature.max() < 1.0 / 12.0
    assert heading[-1] == pytest.approx(np.arctan2(10.0, 100.0), abs=1e-12)
    np.testing.assert_allclose(xy[-1], [200.0, 10.0], atol=1e-9)


def test_impossible_corners_are_refused():
    with pytest.raises(ValueError, match="need .* of their 10.00 m segment"):
        PolylineRoute([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]], corner_radius=12.0, closed=True)
    with pytest.raises(ValueError, match="turns 174.3 deg, more than 170"):
        PolylineRoute([[0.0, 0.0], [100.0, 0.0], [0.0, 10.0]], corner_radius=1.0, closed=False)
    with pytest.raises(ValueError, match="coincide"):
        PolylineRoute([[0.0, 0.0], [100.0, 0.0], [100.0, 0.0]], corner_radius=1.0, closed=False)


def test_a_start_in_motion_has_full_speed_at_time_zero():
    route = PolylineRoute([[0.0, 0.0], [500.0, 0.0]], corner_radius=1.0, closed=False)
    trajectory = Trajectory(route, speed=1.4, accel_time=0.0, lane_offset=0.0)
    assert trajectory.time_at(1.4) == pytest.approx(1.0)
    np.testing.assert_allclose(trajectory.distance(np.array([-1.0, 0.0, 1e-3, 10.0])), [0.0, 0.0, 1.4e-3, 14.0])
    first = trajectory.poses([0.0, 1e-3])[:, :3, 3]
    assert np.linalg.norm(first[1] - first[0]) == pytest.approx(1.4e-3)
    sequence = make_sequence(World(np.zeros((0, 6)), (-1.0, -1.0, 1.0, 1.0)), route, speed=1.4, distance=14.0,
                             accel_time=0.0)  # fmt: skip
    assert isinstance(sequence, SimulatedSequence) and len(sequence) == 100
    np.testing.assert_allclose(np.diff(sequence.ground_truth[:, 0, 3]), 0.14)


def test_walking_sway_stays_within_its_amplitudes_and_the_mount_pitches_the_sensor_down():
    route = PolylineRoute([[0.0, 0.0], [500.0, 0.0]], corner_radius=1.0, closed=False)
    sway = random_sway(np.random.default_rng(7), bob=0.03, lateral=0.05, yaw_deg=4.0)
    assert 1.8 <= sway[0, 1] <= 2.0 and sway[1, 1] == sway[2, 1] == 0.5 * sway[0, 1]
    trajectory = Trajectory(route, speed=1.4, accel_time=0.0, lane_offset=0.0, sway=sway, mount_pitch_deg=12.0)
    T = trajectory.poses(np.linspace(0.0, 30.0, 30001))
    bob, lateral = T[:, 2, 3] - trajectory.sensor_height, T[:, 1, 3]
    forward = T[:, :3, :3] @ np.array([1.0, 0.0, 0.0])
    yaw, pitch = np.rad2deg(np.arctan2(forward[:, 1], forward[:, 0])), np.rad2deg(-np.arcsin(forward[:, 2]))
    for values, amplitude in ((bob, 0.03), (lateral, 0.05), (yaw, 4.0)):
        assert np.abs(values).max() <= amplitude + 1e-12 and np.abs(values).max() > 0.99 * amplitude
    assert np.count_nonzero(np.diff(np.sign(bob))) == pytest.approx(2 * 30.0 * sway[0, 1], abs=2)  # steps
    np.testing.assert_allclose(pitch, 12.0, atol=1e-9)  # no wobble: the mount alone
