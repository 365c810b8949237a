"""The ray-cast LiDAR simulator: determinism, scan shape, ground truth, and the time conventions."""

import numpy as np
import pytest
from kiss_icp.preprocess import Preprocessor

from pipelines.simulation import Route, SimulatedSequence, simulate_sequence


@pytest.fixture(scope="module")
def clean() -> SimulatedSequence:
    """The default drive without range noise or wobble: points lie exactly on the world surface."""
    return simulate_sequence(seed=0, noise_sigma=0.0, wobble_deg=0.0)


def to_world(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by per-point (N, 4, 4) or shared (4, 4) poses."""
    if poses.ndim == 2:
        return points @ poses[:3, :3].T + poses[:3, 3]
    return np.einsum("nij,nj->ni", poses[:, :3, :3], points) + poses[:, :3, 3]


def turning_frame(sequence: SimulatedSequence) -> int:
    """Index of the frame whose sweep turns the most in yaw."""
    start = sequence.ground_truth
    end = sequence.poses_at(sequence.timestamps + sequence.lidar.sweep_period)
    turn = np.abs(np.arctan2(start[:, 1, 0], start[:, 0, 0]) - np.arctan2(end[:, 1, 0], end[:, 0, 0]))
    return int(np.argmax(np.minimum(turn, 2 * np.pi - turn)))


def test_same_seed_gives_identical_frames_in_any_order():
    a = simulate_sequence(seed=3, frames=30)
    b = simulate_sequence(seed=3, frames=30)
    later, earlier = a.frame(25), a.frame(5)
    np.testing.assert_array_equal(later.points, b.frame(25).points)
    np.testing.assert_array_equal(later.times, b.frame(25).times)
    np.testing.assert_array_equal(earlier.points, b.frame(5).points)
    np.testing.assert_array_equal(a.ground_truth, b.ground_truth)
    other = simulate_sequence(seed=4, frames=30).frame(25)
    assert len(other.points) != len(later.points) or not np.array_equal(other.points, later.points)


def test_default_sequence_length_spacing_and_laps():
    sequence = simulate_sequence()
    assert 780 <= len(sequence) <= 830
    positions = sequence.ground_truth[:, :3, 3]
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    cruise = steps[int(sequence.trajectory.accel_time / sequence.lidar.sweep_period) :]
    assert np.all((cruise > 0.85) & (cruise < 1.05))  # 1 m, shorter on the inside of lap-2 corners
    assert np.median(cruise) == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(positions[:, 2], 1.8)
    lap_end = sequence.poses_at(sequence.trajectory.time_at(sequence.trajectory.route.length))[0]
    np.testing.assert_allclose(lap_end[:3, 3], positions[0], atol=1e-9)  # the loop closes
    # lap 2 runs 1.5 m to the left of lap 1: not an exact replay
    length = sequence.trajectory.route.length
    lap1, lap2 = sequence.poses_at([sequence.trajectory.time_at(d * length) for d in (0.5, 1.5)])
    np.testing.assert_allclose(np.linalg.norm(lap1[:3, 3] - lap2[:3, 3]), 1.5, atol=1e-6)
    assert len(simulate_sequence(laps=1)) == pytest.approx(len(sequence) / 2, abs=10)
    assert len(simulate_sequence(frames=7)) == 7


def test_ground_truth_is_rigid_and_yaw_follows_the_path():
    sequence = simulate_sequence()
    T = sequence.ground_truth
    np.testing.assert_allclose(T, sequence.poses_at(sequence.timestamps))
    R = T[:, :3, :3]
    identity = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), identity, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(T[:, :3, :3]), 1.0)
    velocity = np.diff(T[:, :2, 3], axis=0)
    moving = np.linalg.norm(velocity, axis=1) > 0.5
    heading = np.arctan2(velocity[:, 1], velocity[:, 0])
    mid_yaw = np.arctan2(T[:-1, 1, 0] + T[1:, 1, 0], T[:-1, 0, 0] + T[1:, 0, 0])
    error = np.angle(np.exp(1j * (heading - mid_yaw)))[moving]
    assert np.abs(error).max() < np.deg2rad(1.0)


def test_turns_ramp_the_yaw_rate_through_clothoids():
    """A car cannot step its yaw rate; plain arcs did, and KISS-ICP's constant-velocity deskew then rang
    for ~20 frames after each turn (0.14 m RMS along track)."""
    route = Route(0.0, 0.0, 140.0, 70.0)
    s = np.linspace(0.0, route.length, 40001)
    xy, heading, curvature = route.centreline(s)
    step = s[1] - s[0]
    assert np.abs(np.diff(curvature)).max() <= step / (route.corner_radius * route.transition) + 1e-12
    turned = np.unwrap(heading)
    np.testing.assert_allclose(np.diff(turned), 0.5 * (curvature[1:] + curvature[:-1]) * step, atol=1e-6)
    assert turned[-1] - turned[0] == pytest.approx(2 * np.pi, abs=1e-6)
    np.testing.assert_allclose(xy.min(axis=0), [0.0, 0.0], atol=1e-9)  # the sides stay on the centrelines
    np.testing.assert_allclose(xy.max(axis=0), [140.0, 70.0], atol=1e-9)
    plain = Route(0.0, 0.0, 140.0, 70.0, transition=0.0)
    assert plain.length == pytest.approx(2 * (140.0 + 70.0) - 8 * 12.0 + 2 * np.pi * 12.0)
    assert np.abs(np.diff(plain.centreline(s)[2])).max() == pytest.approx(1 / 12.0)  # the step
    with pytest.raises(ValueError, match="transitions"):
        Route(0.0, 0.0, 140.0, 70.0, transition=20.0)


def test_scan_point_counts_and_times():
    sequence = simulate_sequence(seed=1)
    for index in range(0, len(sequence), 100):
        frame = sequence.frame(index)
        assert frame.timestamp == sequence.timestamps[index]
        assert 15_000 <= len(frame.points) <= 30_000
        assert frame.points.shape == (len(frame.times), 3) and frame.points.dtype == np.float64
        assert np.all(np.isfinite(frame.points))
        assert np.linalg.norm(frame.points, axis=1).max() <= sequence.lidar.max_range + 0.2
        assert frame.times.min() >= 0.0 and frame.times.max() < sequence.lidar.sweep_period
        assert np.all(np.diff(frame.times) >= 0.0)


def test_frames_generator_yields_every_frame_in_order():
    sequence = simulate_sequence(frames=4)
    frames = list(sequence.frames())
    assert [f.timestamp for f in frames] == list(sequence.timestamps)
    np.testing.assert_array_equal(frames[2].points, sequence.frame(2).points)


def test_range_noise_has_the_requested_sigma(clean):
    noisy = simulate_sequence(seed=0, noise_sigma=0.02, wobble_deg=0.0)
    a, b = clean.frame(50), noisy.frame(50)
    np.testing.assert_array_equal(a.times, b.times)
    range_error = np.linalg.norm(b.points, axis=1) - np.linalg.norm(a.points, axis=1)
    assert np.std(range_error) == pytest.approx(0.02, rel=0.05)


def test_points_at_their_own_time_lie_on_the_world_and_at_the_stamp_do_not(clean):
    index = turning_frame(clean)
    frame = clean.frame(index)
    own = to_world(clean.poses_at(frame.timestamp + frame.times), frame.points)
    assert clean.world.distance(own).max() < 2e-3
    # off the ground: on the ground plane a point moved along the plane still lies on the world
    above = own[:, 2] > 0.3
    stamp_only = clean.world.distance(to_world(clean.ground_truth[index], frame.points[above]))
    assert np.mean(stamp_only > 0.1) > 0.4
    assert np.percentile(stamp_only, 90) > 0.5


def test_kiss_icp_deskews_into_the_sensor_frame_at_the_latest_point(clean):
    """The convention stated in pipelines.simulation.sequence: KISS-ICP, given our relative times and the
    motion from the earliest to the latest point, expresses the scan at time timestamp + times.max().
    (KISS-ICP passes the motion between frame poses, over sweep_period, 0.1 % longer: 7 mm at 80 m here.)"""
    index = turning_frame(clean)
    frame = clean.frame(index)
    t_end = frame.timestamp + frame.times.max()
    previous, current = clean.poses_at([t_end - np.ptp(frame.times), t_end])
    deskewed = Preprocessor(max_range=1e3, min_range=0.0, deskew=True, max_num_threads=0).preprocess(
        frame.points, frame.times, np.linalg.inv(previous) @ current
    )
    assert clean.world.distance(to_world(current, deskewed)).max() < 2e-3


def test_city_repeats_blocks_and_mirrors_them_across_streets_with_variety():
    world = simulate_sequence(frames=1).world
    pitch = 70.0
    boxes = world.boxes
    footprint = (boxes[:, 3] - boxes[:, 0]) * (boxes[:, 4] - boxes[:, 1])
    buildings, poles = boxes[(boxes[:, 5] > 5.0) & (footprint > 50.0)], boxes[np.isclose(footprint, 0.09)]

    def share(moved: np.ndarray, among: np.ndarray) -> float:
        keys = {tuple(np.round(b, 6)) for b in among}
        return float(np.mean([tuple(np.round(b, 6)) in keys for b in moved]))

    def west_block(b: np.ndarray) -> np.ndarray:
        return b[(b[:, 0] > 0.0) & (b[:, 3] < pitch) & (b[:, 1] > 0.0) & (b[:, 4] < pitch)]

    def mirrored(b: np.ndarray) -> np.ndarray:  # across the street x = 70
        m = b.copy()
        m[:, [0, 3]] = 2 * pitch - b[:, [3, 0]]
        return m

    def repeated(b: np.ndarray) -> np.ndarray:  # two blocks further east
        return b + [2 * pitch, 0, 0, 2 * pitch, 0, 0]

    west = west_block(buildings)
    assert share(mirrored(west), buildings) > 0.6 and share(repeated(west), buildings) > 0.6
    assert len(np.unique(np.round(buildings[:, 5], 6))) > 8  # per-block changes on a 4-height template
    assert share(mirrored(west_block(poles)), poles) < 0.2  # street furniture does not repeat
