"""Poses recorded in a bag: the odometry a front end publishes (FAST-LIO2's /Odometry, LIO-SAM's
/lio_sam/mapping/odometry: nav_msgs/Odometry) or a ground truth (geometry_msgs PoseStamped,
PoseWithCovarianceStamped, TransformStamped), read as (times [s], T_world_frame (N, 4, 4)) like a TUM file.

Each message's time is its header.stamp, or the time it was recorded where header.stamp never changes (the rule
`BagScans` follows for scans); the poses are sorted by time, a pose stamped like the one before replaces it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.io.bags.reader import BagError, one_line, open_reader
from pipelines.io.trajectory import poses_from_rows

ODOMETRY = "nav_msgs/msg/Odometry"
POSE_TYPES = (
    ODOMETRY,
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
)


class NotAPoseTopic(BagError):
    """A topic that is not a topic of poses; `listing` names those the bag has."""

    def __init__(self, message: str, listing: str) -> None:
        super().__init__(message)
        self.listing = listing


_TOPIC_NAME = re.compile(r"/?[A-Za-z~][A-Za-z0-9_~]*(/[A-Za-z_][A-Za-z0-9_]*)*")  # ROS names hold no dots


def is_topic_name(text: str) -> bool:
    """Whether `text` can be a ROS topic name (letters, digits, _ and / only; no file name with a suffix is one)."""
    return _TOPIC_NAME.fullmatch(text) is not None


def pose_topics(path: str | Path) -> dict[str, str]:
    """The topics of a bag whose messages carry a stamped pose (`POSE_TYPES`): {topic: message type}; BagError if the
    bag cannot be read."""
    reader = open_reader(Path(path))
    try:
        return topics_of_poses(reader)
    finally:
        reader.close()


def topics_of_poses(reader: Any) -> dict[str, str]:
    """{topic: message type} of an open AnyReader's topics of `POSE_TYPES` that hold messages."""
    return {name: info.msgtype for name, info in reader.topics.items() if info.msgtype in POSE_TYPES and info.msgcount}


def _pose_row(msg: Any, msgtype: str) -> list[float]:
    """x y z qx qy qz qw of one message."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        position, orientation = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
        position, orientation = pose.position, pose.orientation
    return [position.x, position.y, position.z, orientation.x, orientation.y, orientation.z, orientation.w]


def read_pose_topic(path: str | Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,) [s], poses (N, 4, 4)) of the pose messages on `topic` of the bag at `path`: T_world_frame of the
    message's child frame (Odometry, TransformStamped) or of its header's frame's pose (PoseStamped, ...).

    Raises:
        BagError: the bag cannot be read; `topic` is not a topic of stamped poses (NotAPoseTopic: the message lists
            those the bag has); a message without a valid pose (a quaternion of length far from 1, a non-finite
            number).
    """
    times, poses, _ = read_pose_messages(path, topic)
    return times, poses


def read_pose_messages(path: str | Path, topic: str) -> tuple[np.ndarray, np.ndarray, str | None]:
    """`read_pose_topic`'s (times, poses) and the frame whose poses they are where the messages name it: the
    child_frame_id of the first nav_msgs/Odometry or TransformStamped message; None for the other types.

    Raises:
        BagError: as `read_pose_topic`.
    """
    path = Path(path)
    reader = open_reader(path)
    try:
        available = topics_of_poses(reader)
        if topic not in available:
            listing = ", ".join(f"{name} ({kind.replace('/msg/', '/')})" for name, kind in available.items()) or "none"
            raise NotAPoseTopic(
                f"{path}: {topic} is not a topic of poses in the bag (topics of poses: {listing})", listing
            )
        msgtype = available[topic]
        connections = [c for c in reader.connections if c.topic == topic]
        stamps, recorded, rows, frame = [], [], [], None
        try:
            for connection, record_ns, raw in reader.messages(connections):
                msg = reader.deserialize(raw, connection.msgtype)
                if not stamps and msgtype in (ODOMETRY, "geometry_msgs/msg/TransformStamped"):
                    frame = str(msg.child_frame_id) or None
                stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
                recorded.append(record_ns)
                rows.append(_pose_row(msg, msgtype))
        except Exception as error:  # corrupt or truncated data: rosbags raises many types
            raise BagError(f"{path}: {topic}: corrupt or truncated bag ({one_line(error)})") from None
    finally:
        reader.close()
    times_ns = np.array(recorded if len(set(stamps)) == 1 and len(stamps) > 1 else stamps, dtype=np.int64)
    rows = np.array(rows, dtype=np.float64).reshape(-1, 7)
    norms = np.linalg.norm(rows[:, 3:], axis=1)
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1) | (np.abs(norms - 1.0) > 0.01))
    if len(bad):
        raise BagError(f"{path}: {topic} message {bad[0]}: not a valid pose (a non-finite number or a quaternion of "
                       f"length {norms[bad[0]]:.3g})")  # fmt: skip
    order = np.argsort(times_ns, kind="stable")
    times_ns, rows = times_ns[order], rows[order]
    last_of_each = np.append(np.diff(times_ns) > 0, True)  # of poses stamped alike, the one recorded last
    seconds, nanoseconds = np.divmod(times_ns[last_of_each], 1_000_000_000)
    return seconds + nanoseconds * 1e-9, poses_from_rows(rows[last_of_each]), frame
