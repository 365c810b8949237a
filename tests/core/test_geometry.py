"""Rigid-transform helpers: point transforms, rotation angles, the weighted rigid fit."""

import numpy as np
from scipy.spatial.transform import Rotation

from sandro_core.geometry import rigid_fit, rotation_angle, transform_points


def _transform(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(scale=10.0, size=3)
    return T


def test_transform_points_matches_homogeneous_coordinates():
    rng = np.random.default_rng(0)
    T, points = _transform(rng), rng.normal(size=(20, 3))
    expected = (T @ np.c_[points, np.ones(20)].T).T[:, :3]
    np.testing.assert_allclose(transform_points(T, points), expected, atol=1e-12)


def test_rotation_angle_of_one_and_of_a_stack():
    angles = np.array([0.0, 0.3, 2.0, np.pi])
    R = Rotation.from_rotvec(angles[:, None] * [[0.0, 0.6, 0.8]]).as_matrix()
    np.testing.assert_allclose(rotation_angle(R), angles, atol=1e-7)
    assert isinstance(rotation_angle(R[1]), float) and abs(rotation_angle(R[1]) - 0.3) < 1e-12


def test_rigid_fit_is_exact_and_ignores_zero_weights():
    rng = np.random.default_rng(0)
    T_true = _transform(rng)
    source = rng.normal(size=(50, 3))
    target = transform_points(T_true, source)
    target[:10] += 100.0  # outliers with zero weight
    weights = np.r_[np.zeros(10), rng.uniform(0.5, 2.0, 40)]
    np.testing.assert_allclose(rigid_fit(source, target, weights), T_true, atol=1e-9)
    np.testing.assert_allclose(rigid_fit(source[10:], target[10:]), T_true, atol=1e-9)


def test_rigid_fit_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    source = rng.normal(size=(30, 3))
    mirrored = source * [1.0, 1.0, -1.0]  # best fitted by a reflection, which a rigid fit must not return
    R = rigid_fit(source, mirrored)[:3, :3]
    assert abs(np.linalg.det(R) - 1.0) < 1e-9
