"""FPFH feature correspondences between two point clouds."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

NORMAL_RADIUS_FACTOR = 2.0  # normal estimation radius, in voxel sizes
NORMAL_MAX_NN = 30
FPFH_RADIUS_FACTOR = 5.0  # FPFH radius, in voxel sizes
FPFH_MAX_NN = 100


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {points.shape}")
    if len(points) == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return points


def fpfh_keypoints(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-downsample `points` and compute FPFH descriptors.

    Args:
        points: (N, 3) points [m], any frame.
        voxel_size: voxel edge [m]; normals use a radius of 2 voxels, FPFH one of 5 voxels.

    Returns:
        keypoints (K, 3) float64 in the frame of `points`, and their descriptors (K, 33). Points whose
        descriptor is all zero (no neighbour within the FPFH radius) are left out.
    """
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel_size)
    pcd.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_FACTOR * voxel_size, max_nn=NORMAL_MAX_NN)
    )
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_FACTOR * voxel_size, max_nn=FPFH_MAX_NN)
    )
    descriptors = np.asarray(fpfh.data).T
    keep = np.any(descriptors != 0.0, axis=1)
    return np.asarray(pcd.points)[keep], descriptors[keep]


def match_fpfh(
    source_points: np.ndarray, target_points: np.ndarray, voxel_size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Putative correspondences from mutual nearest neighbours of FPFH descriptors.

    Args:
        source_points: (N, 3) source cloud [m], in the source frame.
        target_points: (M, 3) target cloud [m], in the target frame.
        voxel_size: downsampling voxel [m]; sets the normal (2 voxels) and FPFH (5 voxels) radii.

    Returns:
        (P, Q), both (K, 3) float64: P[i] is a source keypoint (source frame) and Q[i] the target
        keypoint (target frame) whose descriptor is its mutual nearest neighbour. K may be 0.

    Raises:
        ValueError: on empty, non-(N, 3) or non-finite points, or a voxel size that is not a positive number.
    """
    source_points = _check_points(source_points, "source_points")
    target_points = _check_points(target_points, "target_points")
    if not (np.isfinite(voxel_size) and voxel_size > 0.0):
        raise ValueError(f"voxel_size must be a positive finite number [m], got {voxel_size}")

    source_kp, source_desc = fpfh_keypoints(source_points, voxel_size)
    target_kp, target_desc = fpfh_keypoints(target_points, voxel_size)
    if len(source_kp) == 0 or len(target_kp) == 0:
        empty = np.empty((0, 3))
        return empty, empty.copy()

    _, source_to_target = cKDTree(target_desc).query(source_desc, k=1)
    _, target_to_source = cKDTree(source_desc).query(target_desc, k=1)
    mutual = np.flatnonzero(target_to_source[source_to_target] == np.arange(len(source_kp)))
    return source_kp[mutual], target_kp[source_to_target[mutual]]
