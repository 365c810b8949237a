"""Accuracy metrics: ATE, RPE, pose errors, interpolation of a timed trajectory."""

import numpy as np
from scipy.spatial.transform import Rotation

from pipelines.evaluation import ate, pose_errors, rpe
from pipelines.simulation.correspondences import random_transform
from sandro_core.geometry import interpolate_poses


def test_ate_ignores_a_rigid_offset_and_rpe_sees_local_errors(walk):
    poses = walk()
    moved = random_transform(np.random.default_rng(1), 50.0) @ poses
    assert ate(moved, poses) < 1e-9
    assert rpe(moved, poses) < 1e-9
    noisy = poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(2).normal(scale=0.1, size=(len(poses), 3))
    assert 0.05 < ate(noisy, poses) < 0.2


def test_pose_errors():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
    T[:3, 3] = [0.3, 0.4, 0.0]
    rotation, translation = pose_errors(T, np.eye(4))
    assert abs(rotation - 3.0) < 1e-9
    assert abs(translation - 0.5) < 1e-12


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
