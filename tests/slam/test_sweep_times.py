"""sandro_slam.sweep_times: per-point times from the azimuth for raw sweeps without them."""

import numpy as np
import pytest

from pipelines.evaluation import ate
from pipelines.simulation import simulate_sequence
from sandro_slam import OfflineSlam, SlamConfig
from sandro_slam.scan import Scan
from sandro_slam.sweep_times import azimuth_times, sweep_period, with_azimuth_times

FRAMES = 120  # of the simulated drive, from rest through its first corners; one clockwise sweep every 0.1 s


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
    errors = {}
    for sweep_times in ("none", "clockwise", "counterclockwise"):
        result = _run(frames, sweep_times)
        assert result.config.sweep_times == sweep_times
        # Poses refer to the sweep's last point once it is deskewed; a raw sweep registered as it is puts its pose
        # near the middle of the sweep.
        shift = result.timestamps - stamps
        if sweep_times == "none":
            assert np.all(shift == 0.0)
            shift = shift + 0.05
        else:
            assert np.all((shift > 0.09) & (shift < 0.1))
        errors[sweep_times] = ate(result.odometry_poses, sequence.poses_at(stamps + shift))
    assert errors["clockwise"] < 0.3 * min(errors["none"], errors["counterclockwise"])
