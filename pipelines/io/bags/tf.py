"""Poses from a bag's transform tree (/tf and /tf_static, tf2_msgs/TFMessage): the pose of one frame in another along
the chain of transforms between them, as (times [s], T_parent_child (N, 4, 4)) like a TUM file.

What a robot's own odometry publishes (a wheel-inertial EKF's odom -> base_link, LIO-SAM's odom -> lidar_link), and
the extrinsics from /tf_static (base_link -> the LiDAR's frame) on the way to the scans' frame.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np

from pipelines.io.bags.reader import BagError, one_line, open_reader
from pipelines.io.trajectory import poses_from_rows
from sandro_core.geometry import interpolate_poses

TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def _frame(name: str) -> str:
    return name.lstrip("/")  # ROS1 frames may carry a leading slash


def read_tf_poses(path: str | Path, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,) [s], T_parent_child (N, 4, 4)): the pose of frame `child` in frame `parent` from the bag's
    tf2_msgs/TFMessage topics, composed along the chain of transforms between them (each one either way). Transforms
    on a topic named .../tf_static, or that never change, are constant; the others are interpolated at the times of
    the moving transform with the most samples on the chain (held at their first or last value beyond their span).

    Raises:
        BagError: the bag cannot be read, has no transforms, or no chain between the frames (the message names
            the frames it has), or no moving transform on the chain.
    """
    path = Path(path)
    parent, child = _frame(parent), _frame(child)
    reader = open_reader(path)
    stamps: dict[tuple[str, str], list[int]] = {}
    rows: dict[tuple[str, str], list[list[float]]] = {}
    static: set[tuple[str, str]] = set()
    try:
        connections = [c for c in reader.connections if c.msgtype == TF_MESSAGE]
        try:
            for connection, _, raw in reader.messages(connections):
                for transform in reader.deserialize(raw, connection.msgtype).transforms:
                    edge = (_frame(transform.header.frame_id), _frame(transform.child_frame_id))
                    t, q = transform.transform.translation, transform.transform.rotation
                    stamps.setdefault(edge, []).append(
                        int(transform.header.stamp.sec) * 1_000_000_000 + int(transform.header.stamp.nanosec)
                    )
                    rows.setdefault(edge, []).append([t.x, t.y, t.z, q.x, q.y, q.z, q.w])
                    if connection.topic.endswith("tf_static"):
                        static.add(edge)
        except Exception as error:  # corrupt or truncated data: rosbags raises many types
            raise BagError(f"{path}: transforms: corrupt or truncated bag ({one_line(error)})") from None
    finally:
        reader.close()
    if not rows:
        raise BagError(f"{path}: no transforms (no {TF_MESSAGE.replace('/msg/', '/')} topic such as /tf)")
    chain = _chain(rows, parent, child)
    if chain is None:
        frames = sorted({frame for edge in rows for frame in edge})
        raise BagError(f"{path}: no chain of transforms from {parent} to {child} (frames: {', '.join(frames)})")
    edges = {}
    for edge, _ in chain:
        values, times_ns = np.array(rows[edge], dtype=np.float64), np.array(stamps[edge], dtype=np.int64)
        if edge not in static:
            order = np.argsort(times_ns, kind="stable")
            last = np.append(np.diff(times_ns[order]) > 0, True)  # of transforms stamped alike, the last
            times_ns, values = times_ns[order][last], values[order][last]
        if edge in static or np.all(values == values[0]):
            edges[edge] = None, poses_from_rows(values[-1:])
        else:
            seconds, nanoseconds = np.divmod(times_ns, 1_000_000_000)
            edges[edge] = seconds + nanoseconds * 1e-9, poses_from_rows(values)
    moving = [edges[edge][0] for edge, _ in chain if edges[edge][0] is not None]
    if not moving:
        raise BagError(f"{path}: every transform from {parent} to {child} is static: no motion to take as odometry")
    times = max(moving, key=len)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    for edge, forward in chain:
        edge_times, edge_poses = edges[edge]
        if edge_times is None:
            step = np.broadcast_to(edge_poses[0], poses.shape)
        else:
            _, step = interpolate_poses(
                edge_times, edge_poses, np.clip(times, edge_times[0], edge_times[-1]), max_gap=np.inf
            )
        poses = poses @ (step if forward else np.linalg.inv(step))
    return times, poses


def _chain(edges, parent: str, child: str) -> list[tuple[tuple[str, str], bool]] | None:
    """The transforms from `parent` to `child`, each (edge, taken forward), by breadth-first search over the tree
    (each transform either way); None without one."""
    neighbours: dict[str, list[tuple[str, tuple[str, str], bool]]] = {}
    for edge in edges:
        neighbours.setdefault(edge[0], []).append((edge[1], edge, True))
        neighbours.setdefault(edge[1], []).append((edge[0], edge, False))
    if parent not in neighbours or child not in neighbours:
        return None
    came_from: dict[str, tuple[str, tuple[str, str], bool] | None] = {parent: None}
    queue = deque([parent])
    while queue:
        frame = queue.popleft()
        if frame == child:
            break
        for nxt, edge, forward in neighbours[frame]:
            if nxt not in came_from:
                came_from[nxt] = (frame, edge, forward)
                queue.append(nxt)
    if child not in came_from:
        return None
    chain, frame = [], child
    while came_from[frame] is not None:
        previous, edge, forward = came_from[frame]
        chain.append((edge, forward))
        frame = previous
    return chain[::-1]
