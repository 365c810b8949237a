"""What a sandro-slam run leaves in its results folder: trajectories, pose graph, loops, map, plot, configuration,
metrics and the session for sandro-merge (docs/cli.md lists them). Every file is written atomically."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from pipelines.io.atomic import atomic_path, write_text_atomic
from pipelines.io.g2o import write_g2o
from pipelines.io.pointclouds import submaps_cloud, write_point_cloud
from pipelines.io.session import write_session
from pipelines.io.trajectory import write_kitti, write_tum
from pipelines.plots import plot_slam
from sandro_slam import SlamConfig, SlamResult

LOOP_FIELDS = [
    "source_key", "target_key", "found_by", "inliers", "overlap", "gnc_weight", "accepted",
    "x", "y", "z", "qx", "qy", "qz", "qw", "var_rx", "var_ry", "var_rz", "var_x", "var_y", "var_z",
]  # fmt: skip


def write_results(
    folder: Path,
    result: SlamResult,
    config: SlamConfig,
    metrics: dict,
    truth: tuple[np.ndarray, np.ndarray] | None,
    map_voxel: float,
) -> None:
    """Every output file of a run into `folder`; `truth` is the ground truth as (mask of the frames it covers,
    poses at them). Adds the map's point count to `metrics` before writing metrics.json, the last file."""
    write_trajectories(folder, result)
    write_graph(folder / "graph.g2o", result)
    write_loops(folder / "loops.csv", result)
    metrics["map_points"] = write_map(folder / "map.ply", result, map_voxel)
    plot_slam(folder / "trajectory.png", result, truth)
    with atomic_path(folder / "config.yaml") as tmp:
        config.to_yaml(tmp)
    write_session(folder, result)
    write_text_atomic(folder / "metrics.json", json.dumps(metrics, indent=2) + "\n")


def write_trajectories(folder: Path, result: SlamResult) -> None:
    """odometry.{tum,kitti} (KISS-ICP alone) and poses.{tum,kitti} (after loop closure): T_world_sensor per frame."""
    for name, poses in (("odometry", result.odometry_poses), ("poses", result.poses)):
        write_tum(folder / f"{name}.tum", result.timestamps, poses)
        write_kitti(folder / f"{name}.kitti", poses)


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
    return write_point_cloud(
        path, submaps_cloud(((kf.points, result.keyframe_poses[kf.key]) for kf in result.keyframes), voxel)
    )
