"""OfflineSlam on the odometry of another front end: poses in order or matched by time, scans it does not cover."""

import numpy as np
import pytest

from pipelines.simulation import simulate_sequence
from sandro_slam import GivenPoses, OfflineSlam, SlamConfig


def _straight(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n, dtype=float)
    return poses


def test_given_poses_in_order_and_by_time():
    poses = _straight(3)
    in_order = GivenPoses(poses)
    np.testing.assert_array_equal(in_order.at(2, 123.0), poses[2])
    with pytest.raises(ValueError, match="only 3 poses"):
        in_order.at(3, 0.0)
    timed = GivenPoses(poses, times=np.array([10.0, 11.0, 12.0]))
    np.testing.assert_allclose(timed.at(0, 11.25)[:3, 3], [1.25, 0.0, 0.0])
    assert timed.at(0, 9.9) is None and timed.at(0, 12.1) is None


@pytest.mark.parametrize(
    ("poses", "times", "message"),
    [(np.eye(4), None, "shape"), (_straight(2), [1.0], "1 odometry times"), (_straight(2), [2.0, 1.0], "increase")],
)
def test_bad_given_poses(poses, times, message):
    with pytest.raises(ValueError, match=message):
        GivenPoses(poses, times)


def test_scans_outside_the_given_odometry_are_skipped():
    sequence = simulate_sequence(seed=2, frames=8)
    scans, truth = zip(*(sequence.deskewed(i) for i in range(len(sequence))))
    stamps = np.array([scan.timestamp for scan in scans])
    config = SlamConfig()
    config.loops.in_background = False
    result = OfflineSlam(config).run(scans, odometry=GivenPoses(np.array(truth[2:7]), stamps[2:7]))
    assert result.skipped_frames == [0, 1, 7]
    np.testing.assert_allclose(result.timestamps, stamps[2:7])
    np.testing.assert_allclose(result.poses, np.array(truth[2:7]), atol=1e-9)


def test_poses_in_order_stay_with_their_scans_where_scans_are_skipped():
    sequence = simulate_sequence(seed=2, frames=8)
    scans, truth = (list(x) for x in zip(*(sequence.deskewed(i) for i in range(len(sequence)))))
    scans[3] = scans[3]._replace(points=np.full((10, 3), np.nan))  # no finite point
    scans[5] = scans[5]._replace(points=scans[5].points[:20])  # too sparse to use
    config = SlamConfig()
    config.loops.in_background = False
    result = OfflineSlam(config).run(scans, odometry=GivenPoses(np.array(truth)))
    assert result.skipped_frames == [3, 5]
    np.testing.assert_allclose(result.poses, np.array(truth)[[0, 1, 2, 4, 6, 7]], atol=1e-9)
