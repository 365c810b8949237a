"""The `session/` subfolder of a sandro-slam results folder: what sandro-merge needs of a run.

session/session.json        format marker, session name, keyframe keys
session/graph.g2o           odometry and loop edges; vertices at the optimised keyframe poses
session/edges.csv           per g2o edge, in file order: kind (odometry / loop) and whether the back end kept it
session/frames.csv          per frame: timestamp [s], keyframe key, T_keyframe_frame (3x4, row-major)
session/submaps/<key>.ply   keyframe submaps, points in the keyframe frame [m], float32
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import gtsam
import numpy as np
import open3d as o3d

from pipelines.io.atomic import atomic_dir
from pipelines.io.g2o import read_g2o, write_g2o
from pipelines.io.pointclouds import write_point_cloud
from sandro_slam import Session, SlamResult
from sandro_slam.session import SessionEdge

FORMAT = "sandro-slam session"
VERSION = 1


def write_session(folder: Path, result: SlamResult) -> None:
    """Write `folder`/session/ (atomically, as a whole) from a SLAM result; the session is named after `folder`."""
    folder = Path(folder)
    save_session(folder, Session.from_result(result, folder.resolve().name))


def save_session(folder: Path, session: Session) -> None:
    """Write `folder`/session/ (atomically, as a whole) from a Session, under its own name."""
    folder = Path(folder)
    with atomic_dir(folder / "session") as out:
        out.mkdir()
        (out / "submaps").mkdir()
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "name": session.name,
            "keys": session.keys,
            "scale": session.scale,
        }
        (out / "session.json").write_text(json.dumps(meta, indent=1))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for key in session.keys:
            values.insert(key, gtsam.Pose3(session.keyframe_poses[key]))
        for edge in session.edges:
            graph.add(edge.factor(edge.target, edge.source))
        write_g2o(out / "graph.g2o", graph, values)
        rows = ["index,kind,target,source,accepted"]
        rows += [f"{i},{e.kind},{e.target},{e.source},{int(e.accepted)}" for i, e in enumerate(session.edges)]
        (out / "edges.csv").write_text("\n".join(rows) + "\n")
        table = np.column_stack(
            [session.timestamps, session.keyframe_of_frame, session.T_keyframe_frame[:, :3, :].reshape(-1, 12)]
        )
        header = "timestamp,keyframe," + ",".join(f"T{r}{c}" for r in range(3) for c in range(4))
        np.savetxt(
            out / "frames.csv", table, fmt=["%.9f", "%d"] + ["%.9g"] * 12, delimiter=",", header=header, comments=""
        )
        for key in session.keys:
            write_point_cloud(out / "submaps" / f"{key}.ply", session.submaps[key], dtype=np.float32)


def read_session(results_folder: Path) -> Session:
    """The session of a sandro-slam results folder; ValueError (one line) for a missing folder, a folder
    written by another tool, or missing or unreadable session files."""
    results_folder = Path(results_folder)
    if not results_folder.is_dir():
        raise ValueError(f"no such session folder: {results_folder}")
    folder = results_folder / "session"
    meta_path = folder / "session.json"
    if not meta_path.is_file():
        raise ValueError(f"{results_folder}: not a sandro-slam results folder (no session/session.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{meta_path}: unreadable ({error})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{meta_path}: not a sandro-slam session (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise ValueError(f"{meta_path}: session format version {meta.get('version')}, this tool reads {VERSION}")
    for name in ("graph.g2o", "edges.csv", "frames.csv", "submaps"):
        if not (folder / name).exists():
            raise ValueError(f"{results_folder}: session/{name} is missing")
    keys = [int(k) for k in meta["keys"]]
    graph, values = read_g2o(folder / "graph.g2o")
    edges = _edges(folder / "edges.csv", graph)
    frames = _frames(folder / "frames.csv")
    poses, submaps = {}, {}
    for key in keys:
        if not values.exists(key):
            raise ValueError(f"{folder / 'graph.g2o'}: no vertex for keyframe {key}")
        poses[key] = values.atPose3(key).matrix()
        path = folder / "submaps" / f"{key}.ply"
        if not path.is_file():
            raise ValueError(f"{results_folder}: session/submaps/{key}.ply is missing")
        submaps[key] = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    T = np.tile(np.eye(4), (len(frames), 1, 1))
    T[:, :3, :] = frames[:, 2:].reshape(-1, 3, 4)
    session = Session(
        str(meta.get("name", results_folder.resolve().name)),
        keys,
        poses,
        submaps,
        edges,
        frames[:, 0].copy(),
        frames[:, 1].astype(np.int64),
        T,
        meta.get("scale"),
    )
    session.check()
    return session


def _edges(path: Path, graph: gtsam.NonlinearFactorGraph) -> list[SessionEdge]:
    rows = list(csv.DictReader(io.StringIO(path.read_text())))
    if len(rows) != graph.size():
        raise ValueError(f"{path}: {len(rows)} rows for {graph.size()} g2o edges")
    edges = []
    for row, index in zip(rows, range(graph.size())):
        factor = graph.at(index)
        target, source = (int(k) for k in factor.keys())
        if (target, source) != (int(row["target"]), int(row["source"])) or row["kind"] not in ("odometry", "loop"):
            raise ValueError(f"{path}: row {index} does not describe g2o edge {target}-{source}")
        covariance = np.asarray(factor.noiseModel().covariance())
        edges.append(
            SessionEdge(target, source, factor.measured().matrix(), covariance, row["kind"], row["accepted"] == "1")
        )
    return edges


def _frames(path: Path) -> np.ndarray:
    try:
        frames = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as error:
        raise ValueError(f"{path}: unreadable ({error})") from None
    if frames.shape[1:] != (14,) or len(frames) == 0:
        raise ValueError(f"{path}: expected 14 columns per frame, found {frames.shape[1:]}")
    return frames
