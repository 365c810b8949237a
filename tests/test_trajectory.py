"""Trajectory files and metrics."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipelines.synthetic import random_transform
from pipelines.trajectory_io import read_trajectory, read_tum, write_kitti, write_tum
from pipelines.trajectory_metrics import ate, interpolate_poses, rpe


def _trajectory(n: int = 50) -> np.ndarray:
    rng = np.random.default_rng(0)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ random_transform(rng, 1.0))
    return np.array(poses)


def test_tum_round_trip(tmp_path):
    poses, stamps = _trajectory(), np.arange(50) * 0.1 + 1e9
    write_tum(tmp_path / "t.tum", stamps, poses)
    read_stamps, read_poses = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(read_stamps, stamps)
    np.testing.assert_allclose(read_poses, poses, atol=1e-8)


def test_kitti_layout(tmp_path):
    poses = _trajectory(3)
    write_kitti(tmp_path / "k.txt", poses)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "k.txt").reshape(3, 3, 4), poses[:, :3, :], atol=1e-8)


def test_not_a_tum_file(tmp_path):
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="8 columns"):
        read_tum(tmp_path / "bad.txt")


def test_ate_ignores_a_rigid_offset_and_rpe_sees_local_errors():
    poses = _trajectory()
    moved = random_transform(np.random.default_rng(1), 50.0) @ poses
    assert ate(moved, poses) < 1e-9
    assert rpe(moved, poses) < 1e-9
    noisy = poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(2).normal(scale=0.1, size=(len(poses), 3))
    assert 0.05 < ate(noisy, poses) < 0.2


def test_kitti_round_trip_and_format_detection(tmp_path):
    poses, stamps = _trajectory(5), np.arange(5) * 0.1
    write_kitti(tmp_path / "k.txt", poses)
    write_tum(tmp_path / "t.txt", stamps, poses)
    times, read = read_trajectory(tmp_path / "k.txt")
    assert times is None
    np.testing.assert_allclose(read, poses, atol=1e-8)
    times, read = read_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(times, stamps)
    np.testing.assert_allclose(read, poses, atol=1e-8)


@pytest.mark.parametrize("text", ["", "1 2 3\n", "a b c d e f g h\n"])
def test_a_file_that_is_no_trajectory(tmp_path, text):
    (tmp_path / "bad.txt").write_text(text)
    with pytest.raises(ValueError, match="bad.txt"):
        read_trajectory(tmp_path / "bad.txt")
    with pytest.raises(ValueError, match="no such"):
        read_trajectory(tmp_path / "missing.txt")


def test_writes_leave_no_partial_file(tmp_path):
    with pytest.raises(ValueError):
        write_tum(tmp_path / "t.tum", np.arange(3), np.zeros((3, 3, 3)))
    assert list(tmp_path.iterdir()) == []


def test_interpolation_of_a_timed_trajectory():
    times = np.arange(0.0, 10.0, 0.01)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, 0, 3] = 3.0 * times
    poses[:, :3, :3] = Rotation.from_euler("z", 0.2 * times[:, None]).as_matrix()
    at = np.array([-1.0, 0.005, 5.555, 9.99, 11.0])
    mask, out = interpolate_poses(times, poses, at)
    assert mask.tolist() == [False, True, True, True, False]
    np.testing.assert_allclose(out[:, 0, 3], 3.0 * at[mask], atol=1e-9)
    np.testing.assert_allclose(Rotation.from_matrix(out[:, :3, :3]).as_euler("xyz")[:, 2], 0.2 * at[mask], atol=1e-9)
    gappy = np.delete(np.arange(len(times)), np.arange(500, 560))  # a 0.61 s hole around 5.555 s
    mask, _ = interpolate_poses(times[gappy], poses[gappy], at, max_gap=0.2)
    assert mask.tolist() == [False, True, False, True, False]
