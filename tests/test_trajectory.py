"""Trajectory files and metrics."""

import numpy as np
import pytest

from pipelines.synthetic import random_transform
from pipelines.trajectory_io import read_tum, write_kitti, write_tum
from pipelines.trajectory_metrics import ate, rpe


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
