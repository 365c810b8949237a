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
Edge = tuple[str, str]  # (parent frame, child frame) of a transform


def frame_name(name: str) -> str:
    """A frame's name without the leading slash ROS1 frames may carry."""
    return name.lstrip("/")


class TransformTree:
    """Every transform of a bag's tf2_msgs/TFMessage topics. Per edge (parent, child): None and T_parent_child
    (1, 4, 4) for a constant transform (on a topic named .../tf_static, or one that never changes), else its times
    (M,) [s] and poses (M, 4, 4), sorted, the last of transforms stamped alike kept."""

    def __init__(self, path: str | Path) -> None:
        """Read the transforms of the bag at `path`; BagError if it cannot be read."""
        self.path = Path(path)
        stamps: dict[Edge, list[int]] = {}
        rows: dict[Edge, list[list[float]]] = {}
        static: set[Edge] = set()
        reader = open_reader(self.path)
        try:
            connections = [c for c in reader.connections if c.msgtype == TF_MESSAGE]
            for connection, _, raw in reader.messages(connections):
                for transform in reader.deserialize(raw, connection.msgtype).transforms:
                    edge = (frame_name(transform.header.frame_id), frame_name(transform.child_frame_id))
                    t, q = transform.transform.translation, transform.transform.rotation
                    stamp = transform.header.stamp
                    stamps.setdefault(edge, []).append(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))
                    rows.setdefault(edge, []).append([t.x, t.y, t.z, q.x, q.y, q.z, q.w])
                    if connection.topic.endswith("tf_static"):
                        static.add(edge)
        except Exception as error:  # corrupt or truncated data: rosbags raises many types
            raise BagError(f"{self.path}: transforms: corrupt or truncated bag ({one_line(error)})") from None
        finally:
            reader.close()
        self.edges: dict[Edge, tuple[np.ndarray | None, np.ndarray]] = {}
        for edge, values in rows.items():
            values, times_ns = np.array(values, dtype=np.float64), np.array(stamps[edge], dtype=np.int64)
            if edge not in static:
                order = np.argsort(times_ns, kind="stable")
                last = np.append(np.diff(times_ns[order]) > 0, True)
                times_ns, values = times_ns[order][last], values[order][last]
            if edge in static or np.all(values == values[0]):
                self.edges[edge] = None, poses_from_rows(values[-1:])
            else:
                seconds, nanoseconds = np.divmod(times_ns, 1_000_000_000)
                self.edges[edge] = seconds + nanoseconds * 1e-9, poses_from_rows(values)

    def frames(self) -> list[str]:
        """Every frame of the tree, sorted."""
        return sorted({frame for edge in self.edges for frame in edge})

    def chain(self, parent: str, child: str) -> list[tuple[Edge, bool]] | None:
        """The transforms from `parent` to `child`, each (edge, taken forward), by breadth-first search over the
        tree (each transform either way); None without one; empty for the same frame."""
        parent, child = frame_name(parent), frame_name(child)
        neighbours: dict[str, list[tuple[str, Edge, bool]]] = {}
        for edge in self.edges:
            neighbours.setdefault(edge[0], []).append((edge[1], edge, True))
            neighbours.setdefault(edge[1], []).append((edge[0], edge, False))
        came_from: dict[str, tuple[str, Edge, bool] | None] = {parent: None}
        queue = deque([parent])
        while queue and child not in came_from:
            frame = queue.popleft()
            for nxt, edge, forward in neighbours.get(frame, []):
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

    def static(self, parent: str, child: str) -> np.ndarray | None:
        """T_parent_child (4x4) where every transform between them is constant; None otherwise or without a chain."""
        chain = self.chain(parent, child)
        if chain is None or any(self.edges[edge][0] is not None for edge, _ in chain):
            return None
        return self._composed(chain, np.zeros(1))[0]

    def poses(self, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
        """(times (N,) [s], T_parent_child (N, 4, 4)) along the chain, at the times of its moving transform with the
        most samples, the other moving ones interpolated (held at their first or last value beyond their span).

        Raises:
            BagError: no transforms, no chain between the frames (the message names the frames there are), or no
                moving transform on it.
        """
        parent, child = frame_name(parent), frame_name(child)
        if not self.edges:
            raise BagError(f"{self.path}: no transforms (no {TF_MESSAGE.replace('/msg/', '/')} topic such as /tf)")
        chain = self.chain(parent, child)
        if chain is None:
            raise BagError(
                f"{self.path}: no chain of transforms from {parent} to {child} (frames: {', '.join(self.frames())})"
            )
        moving = [self.edges[edge][0] for edge, _ in chain if self.edges[edge][0] is not None]
        if not moving:
            raise BagError(f"{self.path}: every transform from {parent} to {child} is static: no motion to take")
        times = max(moving, key=len)
        return times, self._composed(chain, times)

    def _composed(self, chain: list[tuple[Edge, bool]], times: np.ndarray) -> np.ndarray:
        poses = np.tile(np.eye(4), (len(times), 1, 1))
        for edge, forward in chain:
            edge_times, edge_poses = self.edges[edge]
            if edge_times is None:
                step = np.broadcast_to(edge_poses[0], poses.shape)
            else:
                at = np.clip(times, edge_times[0], edge_times[-1])
                _, step = interpolate_poses(edge_times, edge_poses, at, max_gap=np.inf)
            poses = poses @ (step if forward else np.linalg.inv(step))
        return poses


def read_tf_poses(path: str | Path, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
    """`TransformTree(path).poses(parent, child)`: the pose of frame `child` in frame `parent` along the bag's
    transform tree; BagError if there is none (see `TransformTree.poses`)."""
    return TransformTree(path).poses(parent, child)
