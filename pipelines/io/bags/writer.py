"""Writing scans into new ROS bags as sensor_msgs/PointCloud2 or Livox CustomMsg messages (ROS1 .bag, ROS2 sqlite3
or mcap)."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from pipelines.io.atomic import atomic_dir, atomic_path
from pipelines.io.bags.livox import CUSTOM_MSG_TYPES, encode_custom_msg, register_custom_msg
from pipelines.io.bags.pointcloud2 import POINTCLOUD2, encode_pointcloud2, scan_cloud
from sandro_slam.scan import Scan

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")
MESSAGES = ("pointcloud2", "livox")  # sensor_msgs/PointCloud2; Livox CustomMsg (livox_ros_driver's, driver2's in ROS2)


def bag_path(folder: str | Path, stem: str, fmt: str) -> Path:
    """Where `write_bag` puts a bag named `stem` in `folder`: a .bag file for ros1, a bag folder for ros2-*."""
    return Path(folder) / (f"{stem}.bag" if fmt == "ros1" else f"{stem}_{fmt}")


def delete_bag(path: str | Path) -> None:
    """Remove a bag: a ROS1 file or a ROS2 bag folder."""
    path = Path(path)
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink()


def write_bag(
    path: str | Path,
    fmt: str,
    scans: Iterable[Scan],
    topic: str = "/points",
    frame_id: str = "lidar",
    layout: str = "compact",
    overwrite: bool = False,
    message: str = "pointcloud2",
) -> int:
    """Write scans as messages of type `message` (`MESSAGES`) into a new bag; returns the number of messages.

    Args:
        path: a .bag file for fmt "ros1"; a bag folder (not ending in .bag) for "ros2-sqlite3"/"ros2-mcap".
        scans: (stamp [s], points (N, 3) [m], times (N,) [s] relative to the stamp or empty): `Scan`s or tuples,
            consumed one at a time. Each message is recorded when its sweep ends (stamp + max(times)), as a
            driver publishes it, so the record time differs from header.stamp.
        layout: the point layout of PointCloud2 messages (`scan_cloud`).
        overwrite: replace an existing `path`; otherwise FileExistsError.

    Written atomically: under a temporary name beside `path`, renamed at the end, removed on any error or
    KeyboardInterrupt.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown bag format {fmt!r}; choose from {', '.join(FORMATS)}")
    if message not in MESSAGES:
        raise ValueError(f"unknown message {message!r}; choose from {', '.join(MESSAGES)}")
    if (fmt == "ros1") != (path.suffix == ".bag"):
        raise ValueError(f"{path}: a ROS1 bag is a .bag file, a ROS2 bag a folder not ending in .bag")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise FileExistsError(f"{path} exists")
    typestore = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.LATEST)
    msgtype = POINTCLOUD2
    if message == "livox":
        msgtype = CUSTOM_MSG_TYPES[0] if fmt == "ros1" else CUSTOM_MSG_TYPES[1]
        register_custom_msg(typestore, msgtype)

    def encode(stamp: float, points: np.ndarray, times: np.ndarray) -> Any:
        if message == "livox":
            return encode_custom_msg(typestore, msgtype, stamp, points, times, frame_id)
        return encode_pointcloud2(typestore, stamp, scan_cloud(points, times, layout), frame_id)

    if fmt == "ros1":
        with atomic_path(path) as tmp, Writer1(tmp) as writer:
            connection = writer.add_connection(topic, msgtype, typestore=typestore)
            return _write_scans(writer, connection, msgtype, typestore.serialize_ros1, encode, scans)
    plugin = StoragePlugin.SQLITE3 if fmt == "ros2-sqlite3" else StoragePlugin.MCAP
    with atomic_dir(path) as tmp, Writer2(tmp, version=Writer2.VERSION_LATEST, storage_plugin=plugin) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=typestore)
        return _write_scans(writer, connection, msgtype, typestore.serialize_cdr, encode, scans)


def _write_scans(
    writer: Writer1 | Writer2,
    connection: Any,
    msgtype: str,
    serialize: Callable[[Any, str], Any],
    encode: Callable[[float, np.ndarray, np.ndarray], Any],
    scans: Iterable[Scan],
) -> int:
    count = 0
    for stamp, points, times in scans:
        times = np.asarray(times, dtype=np.float64)
        msg = encode(stamp, np.asarray(points), times)
        end = stamp + (float(times.max()) if len(times) else 0.0)
        writer.write(connection, round(end * 1e9), serialize(msg, msgtype))
        count += 1
    return count
