"""Writing scans into new ROS bags as sensor_msgs/PointCloud2 or Livox CustomMsg messages (ROS1 .bag, ROS2 sqlite3
or mcap), and beside them, optionally, a front end's odometry as nav_msgs/Odometry."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from pipelines.io.atomic import atomic_dir, atomic_path
from pipelines.io.bags.livox import CUSTOM_MSG_TYPES, encode_custom_msg, register_custom_msg
from pipelines.io.bags.pointcloud2 import POINTCLOUD2, encode_pointcloud2, ros_header, scan_cloud
from pipelines.io.bags.poses import ODOMETRY
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
    odometry: Iterable[tuple[float, np.ndarray]] | None = None,
    odometry_topic: str = "/odometry",
) -> int:
    """Write scans as messages of type `message` (`MESSAGES`) into a new bag; returns the number of scan messages.

    Args:
        path: a .bag file for fmt "ros1"; a bag folder (not ending in .bag) for "ros2-sqlite3"/"ros2-mcap".
        scans: (stamp [s], points (N, 3) [m], times (N,) [s] relative to the stamp or empty): `Scan`s or tuples,
            consumed one at a time. Each message is recorded when its sweep ends (stamp + max(times)), as a
            driver publishes it, so the record time differs from header.stamp.
        layout: the point layout of PointCloud2 messages (`scan_cloud`).
        odometry: (time [s], T_odom_sensor (4, 4)) pairs in time order, written on `odometry_topic` as
            nav_msgs/Odometry (frame "odom", child frame `frame_id`, recorded at their stamps), as a LiDAR-inertial
            front end publishes its poses beside its deskewed scans; consumed as the scans are, each before the
            first scan recorded after it. ValueError where a time goes back.
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

    serialize = typestore.serialize_ros1 if fmt == "ros1" else typestore.serialize_cdr
    poses = () if odometry is None else _odometry_messages(typestore, serialize, odometry, frame_id)
    if fmt == "ros1":
        with atomic_path(path) as tmp, Writer1(tmp) as writer:
            connection = writer.add_connection(topic, msgtype, typestore=typestore)
            pose_connection = None
            if odometry is not None:
                pose_connection = writer.add_connection(odometry_topic, ODOMETRY, typestore=typestore)
            return _write_scans(writer, connection, msgtype, serialize, encode, scans, pose_connection, poses)
    plugin = StoragePlugin.SQLITE3 if fmt == "ros2-sqlite3" else StoragePlugin.MCAP
    with atomic_dir(path) as tmp, Writer2(tmp, version=Writer2.VERSION_LATEST, storage_plugin=plugin) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=typestore)
        pose_connection = None
        if odometry is not None:
            pose_connection = writer.add_connection(odometry_topic, ODOMETRY, typestore=typestore)
        return _write_scans(writer, connection, msgtype, serialize, encode, scans, pose_connection, poses)


def _odometry_messages(
    typestore: Any, serialize: Callable[[Any, str], Any], odometry: Iterable[tuple[float, np.ndarray]], frame_id: str
) -> Iterator[tuple[int, Any]]:
    """(record time [ns], serialized nav_msgs/Odometry) of each (time [s], T_odom_sensor) pair, one at a time.

    Raises:
        ValueError: a time before the one before it.
    """
    types = typestore.types
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    last = -np.inf
    for stamp, T in odometry:
        if stamp < last:
            raise ValueError(f"odometry times must not go back ({stamp} s after {last} s)")
        last = stamp
        T = np.asarray(T, dtype=np.float64)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        msg = types[ODOMETRY](
            header=ros_header(typestore, stamp, "odom"),
            child_frame_id=frame_id,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
            ),
        )
        yield round(stamp * 1e9), serialize(msg, ODOMETRY)


def _write_scans(
    writer: Writer1 | Writer2,
    connection: Any,
    msgtype: str,
    serialize: Callable[[Any, str], Any],
    encode: Callable[[float, np.ndarray, np.ndarray], Any],
    scans: Iterable[Scan],
    pose_connection: Any = None,
    poses: Iterable[tuple[int, Any]] = (),
) -> int:
    """Write the scans, and the serialized `poses` on `pose_connection` interleaved with them by record time."""
    count, pending = 0, iter(poses)
    pose = next(pending, None)
    for stamp, points, times in scans:
        times = np.asarray(times, dtype=np.float64)
        msg = encode(stamp, np.asarray(points), times)
        end = round((stamp + (float(times.max()) if len(times) else 0.0)) * 1e9)
        while pose is not None and pose[0] <= end:
            writer.write(pose_connection, *pose)
            pose = next(pending, None)
        writer.write(connection, end, serialize(msg, msgtype))
        count += 1
    while pose is not None:
        writer.write(pose_connection, *pose)
        pose = next(pending, None)
    return count
