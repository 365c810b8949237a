"""sandro_slam.sweep_times: per-point times from the azimuth for raw sweeps without them."""

import numpy as np
import pytest

from pipelines.evaluation import ate
from pipelines.simulation import simulate_sequence
from sandro_slam import OfflineSlam, SlamConfig
from sandro_slam.scan import Scan
from sandro_slam.sweep_times import _moving, azimuth_times, detected_rotation, sweep_period, with_azimuth_times

FRAMES = 120  # of the simulated drive, from rest through its first corners; one clockwise sweep every 0.1 s
TEST_FRAMES = 70  # of them for `detected_rotation` alone: 20 residuals


def test_azimuth_times_start_behind_and_turn_once_per_period():
    behind, left, front, right = [-1.0, 1e-9, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]
    points = np.array([behind, left, front, right])
    np.testing.assert_allclose(azimuth_times(points, 0.1, "clockwise"), [0.0, 0.025, 0.05, 0.075], atol=1e-9)
    np.testing.assert_allclose(azimuth_times(points, 0.1, "counterclockwise"), [0.1, 0.075, 0.05, 0.025], atol=1e-9)


def test_scans_with_times_or_without_a_rotation_stay_as_they_are():
    points = np.random.default_rng(0).normal(size=(10, 3))
    timed = Scan(1.0, points, np.linspace(0.0, 0.1, 10))
    assert with_azimuth_times(timed, 0.1, "clockwise") is timed
    plain = Scan(1.0, points, np.empty(0))
    assert with_azimuth_times(plain, 0.1, None) is plain
    assert len(with_azimuth_times(plain, 0.1, "clockwise").times) == 10


def test_only_sweeps_over_which_the_sensor_moved_or_turned_count():
    poses = np.repeat(np.eye(4)[None], 6, axis=0)
    poses[3:, 0, 3] = [0.2, 0.2, 0.2]  # a step of 0.2 voxels into the fourth pose, then standing
    turned = np.array([[np.cos(0.02), -np.sin(0.02)], [np.sin(0.02), np.cos(0.02)]])  # 1.1 deg
    poses[5, :2, :2] = turned
    np.testing.assert_array_equal(_moving(poses, voxel=1.0), [False, False, False, True, False, True])
    assert not _moving(poses, voxel=3.0)[3]  # 0.2 m is no move at a 3 m voxel


def test_the_sweep_period_is_the_median_stamp_spacing():
    assert sweep_period([0.0, 0.1, 0.2, 0.4, 0.5]) == pytest.approx(0.1)
    assert sweep_period([3.0]) == 0.1


def _run(frames, sweep_times: str):
    config = SlamConfig(scale=1.0, sweep_times=sweep_times)
    config.loops.in_background = False
    return OfflineSlam(config).run(frames)


def test_raw_sweeps_without_times_are_deskewed_with_the_direction_set():
    sequence = simulate_sequence(seed=0, frames=FRAMES)
    frames = [Scan(scan.timestamp, scan.points, np.empty(0)) for scan in map(sequence.frame, range(FRAMES))]
    stamps = np.array([frame.timestamp for frame in frames])
    errors, poses = {}, {}
    for sweep_times in ("none", "clockwise", "counterclockwise", "auto"):
        result = _run(frames, sweep_times)
        poses[sweep_times] = result.odometry_poses
        if sweep_times == "auto":  # told from the scans: as set by hand (KISS-ICP's threads add up in any order)
            assert result.config.sweep_times == "clockwise" and result.timings["sweep_test"] > 0.0
            np.testing.assert_allclose(poses["auto"], poses["clockwise"], atol=1e-6)
            continue
        assert result.config.sweep_times == sweep_times and "sweep_test" not in result.timings
        # Poses refer to the middle of the sweep once it is deskewed; a raw sweep registered as it is puts its pose
        # near there too.
        shift = result.timestamps - stamps
        if sweep_times == "none":
            assert np.all(shift == 0.0)
            shift = shift + 0.05
        else:
            assert np.all(np.abs(shift - 0.05) < 0.005)
        errors[sweep_times] = ate(result.odometry_poses, sequence.poses_at(stamps + shift))
    assert errors["clockwise"] < 0.3 * min(errors["none"], errors["counterclockwise"])


@pytest.fixture(scope="module")
def drive():
    return simulate_sequence(seed=0, frames=TEST_FRAMES)


def test_raw_sweeps_are_told_by_the_direction_that_deskews_them(drive):
    raw = [drive.frame(index).points for index in range(TEST_FRAMES)]
    odometry = SlamConfig().resolved(1.0).odometry
    assert detected_rotation(raw, odometry, 0.1) == "clockwise"
    mirrored = [points * [1.0, -1.0, 1.0] for points in raw]  # the same drive seen by a sensor turning the other way
    assert detected_rotation(mirrored, odometry, 0.1) == "counterclockwise"


def test_deskewed_clouds_and_scans_with_times_get_no_azimuth_times(drive):
    deskewed = [drive.deskewed(index)[0].points for index in range(TEST_FRAMES)]
    assert detected_rotation(deskewed, SlamConfig().resolved(1.0).odometry, 0.1) is None
    config = SlamConfig(scale=1.0)
    config.loops.in_background = False
    timed = OfflineSlam(config).run(drive.frame(index) for index in range(40))
    assert timed.config.sweep_times == "none" and "sweep_test" not in timed.timings
