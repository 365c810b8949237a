"""Writing scans into new ROS bags as sensor_msgs/PointCloud2 messages (ROS1 .bag, ROS2 sqlite3 or mcap)."""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from pipelines.io.atomic import atomic_dir, atomic_path
from pipelines.io.bags.pointcloud2 import POINTCLOUD2, encode_pointcloud2, scan_cloud
from sandro_slam.scan import Scan

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")


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
) -> int:
    """Write scans as sensor_msgs/PointCloud2 messages into a new bag; returns the number of messages.

    Args:
        path: a .bag file for fmt "ros1"; a bag folder (not ending in .bag) for "ros2-sqlite3"/"ros2-mcap".
        scans: (stamp [s], points (N, 3) [m], times (N,) [s] relative to the stamp or empty): `Scan`s or tuples,
            consumed one at a time. Each message is recorded when its sweep ends (stamp + max(times)), as a
            driver publishes it, so the record time differs from header.stamp.
        layout: the point layout (`scan_cloud`).
        overwrite: replace an existing `path`; otherwise FileExistsError.

    Written atomically: under a temporary name beside `path`, renamed at the end, removed on any error or
    KeyboardInterrupt.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown bag format {fmt!r}; choose from {', '.join(FORMATS)}")
    if (fmt == "ros1") != (path.suffix == ".bag"):
        raise ValueError(f"{path}: a ROS1 bag is a .bag file, a ROS2 bag a folder not ending in .bag")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise FileExistsError(f"{path} exists")
    if fmt == "ros1":
        typestore = get_typestore(Stores.ROS1_NOETIC)
        with atomic_path(path) as tmp, Writer1(tmp) as writer:
            connection = writer.add_connection(topic, POINTCLOUD2, typestore=typestore)
            return _write_scans(writer, connection, typestore, typestore.serialize_ros1, scans, frame_id, layout)
    typestore = get_typestore(Stores.LATEST)
    plugin = StoragePlugin.SQLITE3 if fmt == "ros2-sqlite3" else StoragePlugin.MCAP
    with atomic_dir(path) as tmp, Writer2(tmp, version=Writer2.VERSION_LATEST, storage_plugin=plugin) as writer:
        connection = writer.add_connection(topic, POINTCLOUD2, typestore=typestore)
        return _write_scans(writer, connection, typestore, typestore.serialize_cdr, scans, frame_id, layout)


def _write_scans(
    writer: Writer1 | Writer2,
    connection: Any,
    typestore: Typestore,
    serialize: Any,
    scans: Iterable[Scan],
    frame_id: str,
    layout: str,
) -> int:
    count = 0
    for stamp, points, times in scans:
        times = np.asarray(times, dtype=np.float64)
        cloud = scan_cloud(np.asarray(points), times, layout)
        msg = encode_pointcloud2(typestore, stamp, cloud, frame_id)
        end = stamp + (float(times.max()) if len(times) else 0.0)
        writer.write(connection, round(end * 1e9), serialize(msg, POINTCLOUD2))
        count += 1
    return count
