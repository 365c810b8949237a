"""What sandro-merge writes into its output folder (docs/cli.md lists the files)."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import numpy as np
import yaml

from pipelines.io.g2o import write_g2o
from pipelines.io.pointclouds import submaps_cloud, write_point_cloud
from pipelines.io.trajectory import write_kitti, write_tum
from pipelines.plots import plot_merges
from sandro_slam import MergeResult, Session, SlamConfig


def write_merge(out: Path, sessions: list[Session], result: MergeResult, config: SlamConfig) -> None:
    """Every output file into the folder `out`: transforms.yaml, trajectories/, graph.g2o, map.ply,
    trajectories.png and summary.json."""
    transforms = {
        name: {
            "T_merged_session": result.T_merged_session[name].tolist(),
            "covariance_first_keyframe": result.covariance[name].tolist(),
        }
        for name in result.joined
    }
    (out / "transforms.yaml").write_text(
        "# T_merged_session maps the session's world frame into the merged frame (the first session's).\n"
        "# covariance_first_keyframe: marginal 6x6 of the session's first keyframe pose in the merged graph,\n"
        "# gtsam Pose3 order [rotation, translation], right perturbation (keyframe frame).\n"
        + yaml.safe_dump(transforms, sort_keys=False)
    )
    (out / "trajectories").mkdir()
    for session in sessions:
        poses = result.frame_poses[session.name]
        write_tum(out / "trajectories" / f"{session.name}.tum", session.timestamps, poses)
        write_kitti(out / "trajectories" / f"{session.name}.kitti", poses)
    write_g2o(out / "graph.g2o", result.graph, result.values)
    write_merged_map(out / "map.ply", sessions, result, config.merge.map_voxel)
    plot_merges(out / "trajectories.png", {"merged trajectories (frame of the first session)": result})
    (out / "summary.json").write_text(json.dumps(merge_summary(result), indent=2) + "\n")


def merge_summary(result: MergeResult) -> dict:
    """What summary.json holds: sessions, inter-session loops and timings."""
    loops = [
        {
            "target": result.names[lp.target_session],
            "target_key": lp.target_key,
            "source": result.names[lp.source_session],
            "source_key": lp.source_key,
            "inliers": lp.inliers,
            "overlap": round(lp.overlap, 3),
            "found_by": lp.found_by,
            "voted": lp.voted,
            "free_space_conflict": None if np.isnan(lp.conflict) else round(lp.conflict, 4),
            "weight": None if np.isnan(lp.weight) else round(lp.weight, 3),
        }
        for lp in result.loops
    ]
    used = [lp for lp in result.loops if not np.isnan(lp.weight)]
    return {
        "sessions": result.names,
        "joined": result.joined,
        "refused": result.refused,
        "keyframes": {name: len(poses) for name, poses in result.keyframe_poses.items()},
        "inter_session_loops_verified": len(result.loops),
        "inter_session_loops_in_graph": len(used),
        "inter_session_loops_accepted": sum(lp.weight >= 0.5 for lp in used),
        "variance_factors": {group: round(factor, 4) for group, factor in result.variance_factors.items()},
        "timings_s": result.timings,
        "loops": loops,
    }


def write_merged_map(path: Path, sessions: list[Session], result: MergeResult, voxel: float) -> int:
    """The submaps at their merged poses, voxelised per session, coloured by session; returns the point count."""
    colours = matplotlib.colormaps["tab10"]
    points, colors = [], []
    for index, session in enumerate(sessions):
        poses = result.keyframe_poses[session.name]
        cloud = submaps_cloud(((session.submaps[k], poses[k]) for k in session.keys), voxel)
        points.append(cloud)
        colors.append(np.tile(colours(index % 10)[:3], (len(cloud), 1)))
    return write_point_cloud(path, np.concatenate(points), np.concatenate(colors))
