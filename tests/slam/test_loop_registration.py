"""sandro_slam.loop_registration: a submap description survives pickling (to worker processes) unchanged; ICP
refinement is not pulled by what only one submap sees, and its residuals are point-to-plane distances."""

import pickle

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from sandro_core.geometry import rotation_angle, transform_points
from sandro_slam.config import SlamConfig
from sandro_slam.loop_registration import _point_to_plane_residuals, describe_submap, icp_registration, register_submaps


def test_a_pickled_description_registers_exactly_as_the_original(drive):
    truth, _, scans = drive
    config = SlamConfig().resolved().registration
    target, source = describe_submap(scans[0], config), describe_submap(scans[1], config)
    copies = [pickle.loads(pickle.dumps(d)) for d in (target, source)]
    for original, copy in zip((target, source), copies):
        np.testing.assert_array_equal(copy.keypoints, original.keypoints)
        np.testing.assert_array_equal(np.asarray(copy.cloud.normals), np.asarray(original.cloud.normals))
        np.testing.assert_array_equal(np.asarray(copy.icp_points.points), np.asarray(original.icp_points.points))
    first, again = register_submaps(target, source, config), register_submaps(*copies, config)
    assert first.accepted == again.accepted
    np.testing.assert_array_equal(again.T_target_source, first.T_target_source)


def _corner(rng: np.random.Generator, n: int) -> np.ndarray:
    """(3n, 3) points on a floor (z = 0) and two walls (x = 0, y = 0), 20 m each way, 2 cm noise [m]."""
    u = rng.uniform(0.0, 20.0, size=(3, n, 2))
    floor = np.column_stack([u[0], np.zeros(n)])
    wall_x = np.column_stack([np.zeros(n), u[1]])
    wall_y = np.column_stack([u[2, :, 0], np.zeros(n), u[2, :, 1]])
    return np.vstack([floor, wall_x, wall_y]) + rng.normal(scale=0.02, size=(3 * n, 3))


def test_icp_ends_at_the_shared_surfaces_when_the_source_sees_more():
    # The source submap also holds a hedge (16 m x 2 m, 0.2-0.8 m high) where the target saw none: within ICP's 1 m
    # correspondence distance of the floor, its points pull plain ICP up by 0.16 m and tilt it by 0.4 deg.
    rng = np.random.default_rng(3)
    config = SlamConfig().resolved().registration
    target = _corner(rng, 6000)
    hedge = np.column_stack([rng.uniform(2.0, 18.0, 1500), rng.uniform(2.0, 4.0, 1500), rng.uniform(0.2, 0.8, 1500)])
    source_in_target = np.vstack([_corner(rng, 6000), hedge])
    T_target_source = np.eye(4)
    T_target_source[:3, :3] = Rotation.from_euler("zyx", [30.0, 2.0, -1.0], degrees=True).as_matrix()
    T_target_source[:3, 3] = [5.0, -3.0, 0.5]
    source = transform_points(np.linalg.inv(T_target_source), source_in_target)
    T, _ = icp_registration(target, source, T_target_source, config)
    error = np.linalg.inv(T_target_source) @ T
    assert np.linalg.norm(error[:3, 3]) < 0.02
    assert np.degrees(rotation_angle(error[:3, :3])) < 0.1


def test_point_to_plane_residuals_are_signed_distances_along_the_target_normals():
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(0.0, 10.0, (50, 2)), np.zeros(50)])
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(floor))
    target.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (50, 1)))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(floor + [0.3, 0.0, 0.05]))
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, -0.02]  # moves the source to 3 cm above the floor; the slide along it does not count
    pairs = np.column_stack([np.arange(0, 50, 2), np.arange(1, 50, 2)])
    residuals = _point_to_plane_residuals(source, target, T, pairs)
    np.testing.assert_allclose(residuals, np.full(25, 0.03), atol=1e-12)
