"""Registering two keyframe submaps with no initial guess: FPFH, SANDRO, ICP refinement, verification."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from sandro_core import register
from sandro_core.features import NORMAL_MAX_NN, NORMAL_RADIUS_FACTOR, fpfh_features, mutual_matches
from sandro_core.geometry import transform_points
from sandro_slam.config import LoopRegistrationConfig

MIN_SUBMAP_POINTS = 10  # a submap with fewer points is not described nor registered
ICP_RELATIVE_TOLERANCE = 1e-4  # relative change of fitness and RMSE that ends ICP (open3d: 1e-6)
ICP_TUKEY_SIGMAS = 4.685  # the robust ICP's Tukey kernel width in robust standard deviations of the residuals
# (Tukey's constant: 95 % efficiency under Gaussian noise)
ICP_MIN_SIGMA = 0.01  # x icp_voxel: the smallest residual scale the kernel takes (exact synthetic clouds)


@dataclass
class SubmapDescription:
    """What registration needs of a submap, computed once per keyframe (all in the keyframe frame)."""

    keypoints: np.ndarray  # (K, 3) FPFH keypoints
    descriptors: np.ndarray  # (K, 33)
    cloud: o3d.geometry.PointCloud  # the keypoints with their normals (the merge's free-space test)
    icp_points: o3d.geometry.PointCloud  # the submap at icp_voxel with normals: both sides of ICP, the overlap check
    tree: cKDTree  # of the descriptors, built once for every pair the keyframe takes part in

    def __getstate__(self) -> dict[str, np.ndarray]:
        """Pickled as arrays (Open3D's clouds do not pickle); the clouds and the tree are rebuilt from them."""
        return {
            "keypoints": self.keypoints,
            "descriptors": self.descriptors,
            "normals": np.asarray(self.cloud.normals),
            "icp_points": np.asarray(self.icp_points.points),
            "icp_normals": np.asarray(self.icp_points.normals),
        }

    def __setstate__(self, state: dict[str, np.ndarray]) -> None:
        arrays = {name: np.array(value) for name, value in state.items()}  # writable copies: Open3D needs them
        self.keypoints, self.descriptors = arrays["keypoints"], arrays["descriptors"]
        self.cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(arrays["keypoints"]))
        self.cloud.normals = o3d.utility.Vector3dVector(arrays["normals"])
        self.icp_points = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(arrays["icp_points"]))
        self.icp_points.normals = o3d.utility.Vector3dVector(arrays["icp_normals"])
        self.tree = cKDTree(self.descriptors)


@dataclass
class PairRegistration:
    """The outcome of registering a source submap onto a target submap."""

    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6 from SANDRO's final weights, gtsam order, right perturbation
    inliers: int
    overlap: float  # share of the source's icp_points within icp_max_distance of the target's, aligned
    accepted: bool
    reason: str  # why it was rejected ("" if accepted)
    time_s: float


def describe_submap(points: np.ndarray, config: LoopRegistrationConfig) -> SubmapDescription:
    """FPFH keypoints, descriptors and normals (oriented towards the keyframe origin) of a submap, and the
    submap at `icp_voxel` with normals."""
    cloud, descriptors = fpfh_features(points, config.fpfh_voxel, np.zeros(3), config.fpfh_max_nn)
    return SubmapDescription(
        np.asarray(cloud.points), descriptors, cloud, _with_normals(points, config.icp_voxel), cKDTree(descriptors)
    )


def register_submaps(
    target: SubmapDescription, source: SubmapDescription, config: LoopRegistrationConfig
) -> PairRegistration:
    """Estimate T_target_source between two submaps and verify it: SANDRO on FPFH matches, then
    point-to-plane ICP of the source's `icp_points` onto the target's, plain and then robust (`_icp`), whose
    fitness is the overlap.

    ICP works at `icp_voxel` on both sides: onto the coarser FPFH keypoints, the loops lie further from the
    truth (docs/benchmarks.md).
    """
    start = time.perf_counter()
    source_idx, target_idx = mutual_matches(source.descriptors, target.descriptors, source.tree, target.tree)
    if len(source_idx) < max(3, config.min_inliers):
        return _rejected(f"{len(source_idx)} FPFH matches", start)
    result = register(source.keypoints[source_idx], target.keypoints[target_idx], config.sandro)
    if not result.valid or len(result.inliers) < config.min_inliers:
        return _rejected(f"{len(result.inliers)} SANDRO inliers", start, result.transformation)
    T = result.transformation
    if config.icp_refine:
        T, overlap = _icp(source.icp_points, target.icp_points, T, config)
    else:
        overlap = o3d.pipelines.registration.evaluate_registration(
            source.icp_points, target.icp_points, config.icp_max_distance, T
        ).fitness
    accepted = overlap >= config.min_overlap
    return PairRegistration(
        T,
        result.covariance,
        len(result.inliers),
        overlap,
        accepted,
        "" if accepted else f"overlap {overlap:.2f}",
        time.perf_counter() - start,
    )


def icp_registration(
    target: np.ndarray, source: np.ndarray, T_target_source: np.ndarray, config: LoopRegistrationConfig
) -> tuple[np.ndarray, float]:
    """(T_target_source, overlap) of `register_submaps`' ICP alone, from a guess: the source submap (N, 3) onto
    the target submap (M, 3), both at `icp_voxel` and in their keyframe frames."""
    source_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)).voxel_down_sample(config.icp_voxel)
    return _icp(source_cloud, _with_normals(target, config.icp_voxel), T_target_source, config)


def register_from_guess(
    target: SubmapDescription, source: SubmapDescription, T_target_source: np.ndarray, config: LoopRegistrationConfig
) -> tuple[np.ndarray, float]:
    """(T_target_source, overlap) of `register_submaps`' ICP alone on two described submaps, from a guess."""
    return _icp(source.icp_points, target.icp_points, T_target_source, config)


def _with_normals(points: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    """`points` (N, 3) at `voxel` [m], with normals as FPFH's (point-to-plane ICP's target side; their signs do
    not matter there)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(NORMAL_RADIUS_FACTOR * voxel, NORMAL_MAX_NN))
    return cloud


def _icp(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: np.ndarray, config: LoopRegistrationConfig
) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP (the target with normals) from T, then again with a Tukey kernel `ICP_TUKEY_SIGMAS`
    robust standard deviations (1.4826 x median absolute residual) of the first one's residuals wide; (the
    transform, its fitness: the overlap).

    Every source point within `icp_max_distance` of the target weighs in plain ICP, also those of what only the
    source sees (the parts of a submap the other one does not share): their residuals reach the correspondence
    distance and pull the transform along the flat directions of a partial overlap. The kernel leaves them out,
    at the scale the residuals of the overlap show."""
    method = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(ICP_RELATIVE_TOLERANCE, ICP_RELATIVE_TOLERANCE)
    with open3d_on_one_thread():
        icp = o3d.pipelines.registration.registration_icp(source, target, config.icp_max_distance, T, method, criteria)
        T = np.asarray(icp.transformation)
        residuals = _point_to_plane_residuals(source, target, T, np.asarray(icp.correspondence_set))
        if len(residuals) == 0:
            return T, icp.fitness
        sigma = max(1.4826 * float(np.median(np.abs(residuals))), ICP_MIN_SIGMA * config.icp_voxel)
        kernel = o3d.pipelines.registration.TukeyLoss(ICP_TUKEY_SIGMAS * sigma)
        robust = o3d.pipelines.registration.TransformationEstimationPointToPlane(kernel)
        icp = o3d.pipelines.registration.registration_icp(source, target, config.icp_max_distance, T, robust, criteria)
    return np.asarray(icp.transformation), icp.fitness


def _point_to_plane_residuals(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: np.ndarray, correspondences: np.ndarray
) -> np.ndarray:
    """Signed distances [m] of the source points moved by T to the tangent plane of their target point, for the
    (source index, target index) rows of `correspondences` (ICP's last: each source point's nearest target point
    within the correspondence distance at T)."""
    points = transform_points(T, np.asarray(source.points)[correspondences[:, 0]])
    offsets = points - np.asarray(target.points)[correspondences[:, 1]]
    return np.einsum("ij,ij->i", offsets, np.asarray(target.normals)[correspondences[:, 1]])


@contextmanager
def open3d_on_one_thread() -> Iterator[None]:
    """Open3D on one thread while the block runs (its previous limit restored after it). On several threads its ICP
    adds up the threads' shares of the normal equations in the order they finish, so that the same input ends 1e-16
    apart from run to run, and the loops' verdicts and the graph after them can differ; on one thread every run
    gives the same result."""
    saved = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(saved)


def _rejected(reason: str, start: float, T: np.ndarray | None = None) -> PairRegistration:
    return PairRegistration(
        np.eye(4) if T is None else T, np.full((6, 6), np.nan), 0, 0.0, False, reason, time.perf_counter() - start
    )
