"""What a sandro-slam run leaves in its results folder: trajectories, pose graph, loops, map and plot.

Every file is written atomically (`pipelines.atomic_write`): a reader never sees half a file.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

import gtsam
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from pipelines.atomic_write import atomic_path
from pipelines.g2o_io import write_g2o
from pipelines.trajectory_io import write_kitti, write_tum
from pipelines.trajectory_metrics import align_se3, ate
from sandro_slam import SlamResult

LOOP_FIELDS = [
    "source_key", "target_key", "found_by", "inliers", "overlap", "gnc_weight", "accepted",
    "x", "y", "z", "qx", "qy", "qz", "qw", "var_rx", "var_ry", "var_rz", "var_x", "var_y", "var_z",
]  # fmt: skip


def write_trajectories(folder: Path, result: SlamResult) -> list[Path]:
    """odometry.{tum,kitti} (KISS-ICP alone) and poses.{tum,kitti} (after loop closure): T_world_sensor per frame."""
    paths = []
    for name, poses in (("odometry", result.odometry_poses), ("poses", result.poses)):
        write_tum(folder / f"{name}.tum", result.timestamps, poses)
        write_kitti(folder / f"{name}.kitti", poses)
        paths += [folder / f"{name}.tum", folder / f"{name}.kitti"]
    return paths


def write_graph(path: Path, result: SlamResult) -> int:
    """The keyframe pose graph as g2o, vertices at the optimised keyframe poses (the prior is left out)."""
    values = gtsam.Values()
    for key, T in result.keyframe_poses.items():
        values.insert(key, gtsam.Pose3(T))
    return write_g2o(path, result.graph, values)


def write_loops(path: Path, result: SlamResult) -> None:
    """loops.csv: one row per verified loop, T_target_source as translation [m] + quaternion (x y z w), the
    diagonal of its covariance (gtsam order: rotation [rad^2], then translation [m^2]), the back end's weight."""
    with atomic_path(path) as tmp, tmp.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(LOOP_FIELDS)
        for loop in result.loops:
            T = loop.T_target_source
            writer.writerow([
                loop.source_key, loop.target_key, loop.found_by, loop.inliers, f"{loop.overlap:.4f}",
                f"{loop.weight:.4f}", int(loop.weight >= 0.5),
                *(f"{v:.6f}" for v in T[:3, 3]), *(f"{v:.9f}" for v in Rotation.from_matrix(T[:3, :3]).as_quat()),
                *(f"{v:.6g}" for v in np.diag(loop.covariance)),
            ])  # fmt: skip


def write_map(path: Path, result: SlamResult, voxel: float) -> int:
    """The keyframe submaps moved to their optimised poses, one point per `voxel` [m], as a PLY; returns the
    number of points."""
    return write_ply(path, submaps_cloud(((kf.points, result.keyframe_poses[kf.key]) for kf in result.keyframes),
                                         voxel))


def submaps_cloud(submaps: Iterable[tuple[np.ndarray, np.ndarray]], voxel: float) -> o3d.geometry.PointCloud:
    """Submaps given as (points in the keyframe frame, T_world_keyframe) moved into the world frame, one point
    per `voxel` [m] (voxelised every 20 submaps on the way: memory stays bounded on long runs)."""
    cloud = o3d.geometry.PointCloud()
    for index, (points, T) in enumerate(submaps):
        cloud.points.extend(o3d.utility.Vector3dVector(points @ T[:3, :3].T + T[:3, 3]))
        if index % 20 == 19:
            cloud = cloud.voxel_down_sample(voxel)
    return cloud.voxel_down_sample(voxel)


def write_ply(path: Path, cloud: o3d.geometry.PointCloud) -> int:
    """Write `cloud` as a PLY, atomically; returns its number of points."""
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), cloud):
            raise OSError(f"could not write {path}")
    return len(cloud.points)


def plot_trajectories(path: Path, result: SlamResult, truth: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """A top view of the trajectory before (odometry) and after loop closure, with accepted (green) and rejected
    (red, dashed) loops between the optimised keyframe positions; the ground truth too when given as
    (mask of the frames it covers, poses at them), SE3-aligned to the optimised trajectory's matched frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if truth is None:
        fig, ax = plt.subplots(figsize=(9, 8))
    else:
        fig, (ax, errors) = plt.subplots(1, 2, figsize=(15, 7), gridspec_kw={"width_ratios": [3, 2]})
        mask, poses = truth
        gt = align_se3(poses, result.poses[mask]) @ poses
        ax.plot(gt[:, 0, 3], gt[:, 1, 3], color="0.6", lw=3, alpha=0.5, label="ground truth")
        _plot_errors(errors, result, mask, poses)
    ax.plot(result.odometry_poses[:, 0, 3], result.odometry_poses[:, 1, 3], color="tab:orange", lw=1,
            label="odometry (KISS-ICP)")
    ax.plot(result.poses[:, 0, 3], result.poses[:, 1, 3], color="tab:blue", lw=1.2, label="after loop closure")
    for accepted, style in ((True, dict(color="tab:green", lw=0.8)), (False, dict(color="tab:red", lw=1, ls="--"))):
        label = "accepted loop" if accepted else "rejected loop"
        for loop in (lp for lp in result.loops if (lp.weight >= 0.5) == accepted):
            a, b = (result.keyframe_poses[k][:3, 3] for k in (loop.source_key, loop.target_key))
            ax.plot([a[0], b[0]], [a[1], b[1]], label=label, **style)
            label = None
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    accepted = sum(loop.weight >= 0.5 for loop in result.loops)
    ax.set_title(f"{len(result.timestamps)} frames, {len(result.keyframes)} keyframes, "
                 f"{accepted} loops accepted, {len(result.loops) - accepted} rejected")
    ax.legend(loc="best")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def _plot_errors(ax, result: SlamResult, mask: np.ndarray, truth: np.ndarray) -> None:
    """Position error [m] over time after an SE3 alignment to the ground truth, before and after loop closure."""
    t = result.timestamps[mask] - result.timestamps[0]
    for name, poses, color in (("odometry", result.odometry_poses[mask], "tab:orange"),
                               ("after loop closure", result.poses[mask], "tab:blue")):
        aligned = align_se3(poses, truth) @ poses
        error = np.linalg.norm(aligned[:, :3, 3] - truth[:, :3, 3], axis=1)
        ax.plot(t, error, color=color, lw=1, label=f"{name} (ATE {ate(poses, truth):.3f} m)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error after SE3 alignment [m]")
    ax.legend(loc="upper left")
