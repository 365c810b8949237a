"""The odometry's pose held to its constant-velocity prediction where the scan constrains translation weakly
(`odometry.with_motion_prior`), with VGICP's Hessian as `GaussianMapRefiner.align` gives it."""

import gtsam
import numpy as np

from sandro_core.geometry import transform_points
from sandro_slam.config import OdometryGicpConfig
from sandro_slam.odometry import GaussianMapRefiner, with_motion_prior

# The sensor turned 90 deg about z: its x axis looks along the world's y, which nothing in the scene below holds.
T_WORLD_SENSOR = gtsam.Pose3(gtsam.Rot3.Yaw(np.radians(90.0)), np.array([1.0, 2.0, 1.5])).matrix()


def _floor_and_wall(rng: np.random.Generator) -> np.ndarray:
    """(N, 3) world points [m]: a floor (z = 0) and one wall (x = 5) along the world's y axis."""
    floor = np.c_[rng.uniform(-10.0, 10.0, size=(4000, 2)), np.zeros(4000)]
    wall = np.c_[np.full(2000, 5.0), rng.uniform(-10.0, 10.0, size=2000), rng.uniform(0.0, 3.0, size=2000)]
    return np.r_[floor, wall] + rng.normal(0.0, 0.01, size=(6000, 3))


def _hessian_at_truth() -> np.ndarray:
    world = _floor_and_wall(np.random.default_rng(0))
    refiner = GaussianMapRefiner(OdometryGicpConfig(resolution=1.0, source_voxel=0.25, max_distance=1.0))
    refiner.insert(refiner.prepared(world), np.eye(4))
    scan = transform_points(np.linalg.inv(T_WORLD_SENSOR), world)
    pose, _, hessian = refiner.align(scan, T_WORLD_SENSOR)
    np.testing.assert_allclose(pose[:3, 3], T_WORLD_SENSOR[:3, 3], atol=0.02)
    return hessian


def test_the_weak_direction_follows_the_prediction_and_the_others_the_registration():
    prediction = T_WORLD_SENSOR
    registered = prediction.copy()
    registered[:3, 3] += [0.05, 0.5, -0.03]  # world x (the wall holds it), y (nothing does), z (the floor)
    moved = with_motion_prior(registered, prediction, _hessian_at_truth(), share=0.03)
    offset = moved[:3, 3] - prediction[:3, 3]
    assert abs(offset[1]) < 0.05  # back at the prediction along the world's y, 0.5 m registered
    np.testing.assert_allclose(offset[[0, 2]], [0.05, -0.03], atol=0.005)  # where the scene holds it
    assert np.degrees(np.arccos(np.clip((np.trace(moved[:3, :3].T @ registered[:3, :3]) - 1) / 2, -1, 1))) < 0.1


def test_a_scan_that_constrains_every_direction_keeps_its_registered_pose():
    prediction = T_WORLD_SENSOR
    registered = prediction.copy()
    registered[:3, 3] += [0.3, -0.2, 0.1]
    hessian = np.diag([50.0, 40.0, 30.0, 10.0, 5.0, 2.0])  # the weakest translation at 0.2 of the strongest
    np.testing.assert_array_equal(with_motion_prior(registered, prediction, hessian, share=0.03), registered)
    np.testing.assert_array_equal(with_motion_prior(registered, prediction, _hessian_at_truth(), 0.0), registered)


def test_the_moved_pose_has_a_rotation_even_where_the_prediction_is_a_little_off():
    # Each pose makes the next prediction; the rounding of their products grew over a walk's 358 scans until
    # KISS-ICP's Sophus refused the rotation as not orthogonal (an abort, not an exception).
    prediction = T_WORLD_SENSOR.copy()
    prediction[:3, :3] *= 1.0 + 1e-9
    registered = prediction.copy()
    registered[:3, 3] += [0.05, 0.5, -0.03]
    moved = with_motion_prior(registered, prediction, _hessian_at_truth(), share=0.03)
    np.testing.assert_allclose(moved[:3, :3].T @ moved[:3, :3], np.eye(3), rtol=0.0, atol=1e-14)
