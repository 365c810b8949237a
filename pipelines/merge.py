"""`sandro-merge`: join sessions recorded at different times into one map, with no initial alignment.

Sessions are sandro-slam results folders (their session/ subfolder) or bags, which are processed first (into
OUT/sessions/). The merged frame is the first session's world frame. Writes into OUT (a new or empty folder,
all or nothing):
    transforms.yaml                 per session: T_merged_session (4x4) and the 6x6 covariance of its first
                                    keyframe's pose (gtsam order [rotation, translation], keyframe frame)
    map.ply                         the keyframe submaps at their merged poses, voxelised, coloured by session
    trajectories/<name>.tum/.kitti  every frame's pose in the merged frame
    graph.g2o                       the merged keyframe graph (keys: gtsam symbols 'a'+session index, key)
    trajectories.png                top view of the merged trajectories with the inter-session loops
    summary.json                    sessions, loops (with weights and free-space conflicts), timings
When a session cannot be joined it says why, exits with 1 and writes nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pipelines.cli import Parser
from pipelines.slam import InputError, load_config
from sandro_slam import MergeResult, Session, SlamConfig, merge_sessions

BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of `sandro-merge`."""
    parser = Parser(prog="sandro-merge", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sessions", type=Path, nargs="+", metavar="SESSION",
                        help="sandro-slam results folder or bag (at least two)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (new or empty)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (its merge section; default: built-in values)")
    parser.add_argument("--topic", help="PointCloud2 topic of bags given as sessions")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; exit code 0 merged, 1 refused (sessions do not join), 2 bad input."""
    args = build_parser().parse_args(argv)
    try:
        if len(args.sessions) < 2:
            raise ValueError("at least two sessions are needed")
        if args.out.exists() and (not args.out.is_dir() or any(args.out.iterdir())):
            raise ValueError(f"{args.out} exists and is not an empty folder: refusing to overwrite it")
        config = load_config(args.config)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        from pipelines.atomic_write import atomic_dir

        with atomic_dir(args.out) as out:
            out.mkdir()
            sessions = [_load_session(path, out / "sessions", config, args.topic) for path in args.sessions]
            _unique_names(sessions)
            result = merge_sessions(sessions, config)
            if not result.ok:
                raise _Refused("; ".join(f"{name}: {why}" for name, why in result.refused.items()))
            write_outputs(out, sessions, result, config)
    except _Refused as refused:
        print(f"sandro-merge: refused, nothing written: {refused}", file=sys.stderr)
        return 1
    except (InputError, ValueError, OSError) as error:
        print(f"sandro-merge: error: {_one_line(error)}", file=sys.stderr)
        return 2
    print_summary(args.out, result)
    return 0


class _Refused(Exception):
    """The sessions could not be joined."""


def _one_line(error: Exception) -> str:
    text = str(error).strip() or type(error).__name__
    return text.splitlines()[0]


def _is_bag(path: Path) -> bool:
    return (path.is_file() and path.suffix in BAG_SUFFIXES) or (path.is_dir() and (path / "metadata.yaml").is_file())


def _load_session(path: Path, bag_out: Path, config: SlamConfig, topic: str | None) -> Session:
    """A results folder's session, or a bag's after running sandro-slam on it into `bag_out`."""
    from pipelines.session_io import read_session

    if _is_bag(path):
        from pipelines.slam import run_bag

        print(f"sandro-merge: processing bag {path} ...", flush=True)
        try:
            folder, _ = run_bag(path, bag_out, config, topic)
        except Exception as error:  # the bag reader's own errors: one line, like the other bad inputs
            raise ValueError(f"{path}: {_one_line(error)}") from None
        return read_session(folder)
    return read_session(path)


def _unique_names(sessions: list[Session]) -> None:
    seen: dict[str, int] = {}
    for session in sessions:
        count = seen.get(session.name, 0)
        seen[session.name] = count + 1
        if count:
            session.name = f"{session.name}-{count}"


def write_outputs(out: Path, sessions: list[Session], result: MergeResult, config: SlamConfig) -> None:
    """Every output file (see the module docstring) into the folder `out`."""
    import yaml

    from pipelines.g2o_io import write_g2o
    from pipelines.trajectory_io import write_kitti, write_tum

    transforms = {name: {"T_merged_session": result.T_merged_session[name].tolist(),
                         "covariance_first_keyframe": result.covariance[name].tolist()} for name in result.joined}
    (out / "transforms.yaml").write_text(
        "# T_merged_session maps the session's world frame into the merged frame (the first session's).\n"
        "# covariance_first_keyframe: marginal 6x6 of the session's first keyframe pose in the merged graph,\n"
        "# gtsam Pose3 order [rotation, translation], right perturbation (keyframe frame).\n"
        + yaml.safe_dump(transforms, sort_keys=False))
    (out / "trajectories").mkdir()
    for session in sessions:
        poses = result.frame_poses[session.name]
        write_tum(out / "trajectories" / f"{session.name}.tum", session.timestamps, poses)
        write_kitti(out / "trajectories" / f"{session.name}.kitti", poses)
    write_g2o(out / "graph.g2o", result.graph, result.values)
    write_map(out / "map.ply", sessions, result, config.merge.map_voxel)
    plot_merge(out / "trajectories.png", result)
    (out / "summary.json").write_text(json.dumps(summary(result), indent=2) + "\n")


def summary(result: MergeResult) -> dict:
    """What summary.json holds: sessions, inter-session loops and timings."""
    loops = [{"target": result.names[lp.target_session], "target_key": lp.target_key,
              "source": result.names[lp.source_session], "source_key": lp.source_key, "inliers": lp.inliers,
              "overlap": round(lp.overlap, 3), "found_by": lp.found_by, "voted": lp.voted,
              "free_space_conflict": None if np.isnan(lp.conflict) else round(lp.conflict, 4),
              "weight": None if np.isnan(lp.weight) else round(lp.weight, 3)} for lp in result.loops]
    used = [lp for lp in result.loops if not np.isnan(lp.weight)]
    return {
        "sessions": result.names,
        "joined": result.joined,
        "refused": result.refused,
        "keyframes": {name: len(poses) for name, poses in result.keyframe_poses.items()},
        "inter_session_loops_verified": len(result.loops),
        "inter_session_loops_in_graph": len(used),
        "inter_session_loops_accepted": sum(lp.weight >= 0.5 for lp in used),
        "timings_s": result.timings,
        "loops": loops,
    }


def write_map(path: Path, sessions: list[Session], result: MergeResult, voxel: float) -> int:
    """The submaps at their merged poses, voxelised per session, coloured by session; returns the point count."""
    import matplotlib
    import open3d as o3d

    from pipelines.slam_outputs import submaps_cloud, write_ply

    colours = matplotlib.colormaps["tab10"]
    merged = o3d.geometry.PointCloud()
    for index, session in enumerate(sessions):
        poses = result.keyframe_poses[session.name]
        cloud = submaps_cloud(((session.submaps[k], poses[k]) for k in session.keys), voxel)
        cloud.paint_uniform_color(colours(index % 10)[:3])
        merged += cloud
    return write_ply(path, merged)


def plot_merge(path: Path, result: MergeResult) -> None:
    """Top view of every session's merged trajectory and the inter-session loops (kept: solid, rejected: dotted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipelines.atomic_write import atomic_path

    fig, ax = plt.subplots(figsize=(9, 8))
    for name in result.joined:
        poses = result.frame_poses[name]
        ax.plot(poses[:, 0, 3], poses[:, 1, 3], lw=1.2, label=name)
    for loop in result.loops:
        if np.isnan(loop.weight):
            continue
        a = result.keyframe_poses[result.names[loop.target_session]][loop.target_key][:2, 3]
        b = result.keyframe_poses[result.names[loop.source_session]][loop.source_key][:2, 3]
        kept = loop.weight >= 0.5
        ax.plot([a[0], b[0]], [a[1], b[1]], "k-" if kept else "r:", lw=0.8 if kept else 1.0)
    ax.plot([], [], "k-", label="inter-session loop")
    ax.plot([], [], "r:", label="rejected by the back end")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend()
    ax.set_title("merged trajectories (frame of the first session)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def print_summary(out: Path, result: MergeResult) -> None:
    """A few lines on stdout: each session's transform and the loops that joined it."""
    info = summary(result)
    print(f"sandro-merge: {len(result.joined)} sessions joined in {result.timings['total']:.1f} s "
          f"({info['inter_session_loops_accepted']} inter-session loops kept of {info['inter_session_loops_verified']}"
          " verified)")
    for name in result.joined:
        T = result.T_merged_session[name]
        yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
        sigma = np.sqrt(np.diag(result.covariance[name])[3:])
        print(f"  {name}: t = [{T[0, 3]:.2f}, {T[1, 3]:.2f}, {T[2, 3]:.2f}] m, yaw {yaw:.1f} deg, "
              f"sigma_t {np.linalg.norm(sigma):.3f} m")
    print(f"results in {out}")


if __name__ == "__main__":
    sys.exit(main())
