"""OfflineSlam on the odometry of another front end: poses in order or matched by time, scans it does not cover."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipelines.simulation import simulate_sequence
from sandro_slam import GivenPoses, OfflineSlam, Scan, SlamConfig
from sandro_slam.odometry import GivenOdometry


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


def test_timed_poses_deskew_a_raw_scan():
    # A sensor turning and moving through a fixed set of points; each point seen at its own time of the sweep.
    times = np.arange(0.0, 0.1, 1e-4)  # on the rounding step: exact
    rng = np.random.default_rng(0)
    world = rng.uniform(-20.0, 20.0, (len(times), 3))
    pose_times = np.array([9.95, 10.0, 10.05, 10.1, 10.15])
    poses = np.tile(np.eye(4), (5, 1, 1))
    angles = 0.5 * (pose_times - 10.0)  # 0.5 rad/s yaw, 8 m/s along x
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = (
        np.cos(angles), -np.sin(angles), np.sin(angles), np.cos(angles))  # fmt: skip
    poses[:, 0, 3] = 8.0 * (pose_times - 10.0)
    given = GivenPoses(poses, pose_times)
    at_point = np.array([given.at(0, 10.0 + t) for t in times])
    raw = np.einsum("nji,nj->ni", at_point[:, :3, :3], world - at_point[:, :3, 3])  # each point in its own frame
    scan = Scan(10.0, raw, times)
    T_world_scan = given.at(0, scan.timestamp)
    expected = (world - T_world_scan[:3, 3]) @ T_world_scan[:3, :3]  # the world points in the frame at the stamp
    np.testing.assert_allclose(given.deskew(scan, T_world_scan), expected, atol=1e-9)
    with pytest.raises(ValueError, match="no times"):
        GivenPoses(poses).deskew(scan, T_world_scan)


@pytest.mark.parametrize("deskew", [True, False])
def test_raw_scans_on_timed_poses_are_deskewed_unless_turned_off(deskew):
    sequence = simulate_sequence(seed=2, frames=3)
    frame = sequence.frame(2)
    stamps = np.arange(0.0, 0.4, 0.005)  # true poses at 200 Hz, as an inertial front end publishes them
    given = GivenPoses(sequence.poses_at(stamps), stamps)
    odometry = GivenOdometry(given, submap_voxel=1e-3, deskew=deskew)
    [(stamp, pose, points)] = odometry.add(frame)
    truly, T_world_end = sequence.deskew(frame)  # deskewed with the true motion, at the sweep's end
    T_pose_end = np.linalg.inv(pose) @ T_world_end
    expected = truly.points @ T_pose_end[:3, :3].T + T_pose_end[:3, 3]
    gaps = cKDTree(expected).query(points)[0]
    assert stamp == frame.timestamp and np.allclose(pose, given.at(0, frame.timestamp))
    if deskew:
        assert np.median(gaps) < 1e-3
    else:
        assert np.median(gaps) > 0.01  # the sweep's motion left in (nearest points lie closer than it)
