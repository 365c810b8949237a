"""Livox CustomMsg to and from numpy: the point message of Livox's ROS drivers (livox_ros_driver, livox_ros_driver2,
livox_ros2_driver), which FAST-LIO and most Livox recordings use instead of sensor_msgs/PointCloud2.

A CustomMsg holds a header, `timebase` (uint64, ns: the time of its first point) and a list of points, each
`offset_time` (uint32, ns after timebase), x, y, z (float32, m, sensor frame), reflectivity, tag and line (uint8).
The points are decoded straight from the serialized bytes with a strided numpy view (ROS1 packs a point into 19
bytes, CDR aligns each to 20); rosbags' generic deserialisation builds one Python object a point, some 40 ms for
a 24000-point Avia scan.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from rosbags.typesys import get_types_from_msg
from rosbags.typesys.store import Typestore

from pipelines.io.bags.pointcloud2 import ros_header
from pipelines.io.lidar_points import nanoseconds_after_stamp, relative_seconds, returns

CUSTOM_MSG_TYPES = (
    "livox_ros_driver/msg/CustomMsg",
    "livox_ros_driver2/msg/CustomMsg",
    "livox_interfaces/msg/CustomMsg",
)
_POINT_MSG = """uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
_CUSTOM_MSG = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
_POINT_NAMES = ["offset_time", "x", "y", "z", "tag"]
_POINT_FORMATS = ["u4", "f4", "f4", "f4", "u1"]
_POINT_OFFSETS = [0, 4, 8, 12, 17]
_POINT_SIZE = 19  # offset_time, x, y, z, reflectivity, tag, line
_FRAME_ID_AT = 16  # byte of header.frame_id's text, in ROS1 and in CDR bytes alike


class CustomMsgError(ValueError):
    """A serialized CustomMsg whose points cannot be decoded; the message says why in one line."""


def register_custom_msg(typestore: Typestore, msgtype: str = CUSTOM_MSG_TYPES[0]) -> None:
    """Add the CustomMsg `msgtype` (one of CUSTOM_MSG_TYPES) and its CustomPoint to `typestore`, to write them."""
    package = msgtype.split("/")[0]
    types = get_types_from_msg(_POINT_MSG, f"{package}/msg/CustomPoint")
    types.update(get_types_from_msg(_CUSTOM_MSG, msgtype))
    typestore.register(types)


def custom_msg_arrays(raw: bytes | memoryview, cdr: bool) -> tuple[int, np.ndarray, np.ndarray]:
    """(header.stamp [ns], points (N, 3) float64 [m], times (N,) float64 [s] relative to header.stamp, or empty)
    of one serialized CustomMsg: ROS1 serialisation (`cdr` False) or ROS2 CDR of either byte order.

    Points that are not finite, exactly at the origin (no return) or tagged as noise by the sensor
    (`lidar_points.livox_noise`) are dropped with their times. Times are empty
    when every point has the same offset_time (a driver that does not fill it).

    Raises:
        CustomMsgError: fewer bytes than the header and the points it announces need.
    """
    data = memoryview(raw).cast("B")
    try:
        stamp_ns, timebase, count, start, order, stride = (_cdr_layout if cdr else _ros1_layout)(data)
    except struct.error:
        raise CustomMsgError(f"CustomMsg of {data.nbytes} bytes ends inside its header") from None
    needed = start + (count - 1) * stride + _POINT_SIZE if count else start
    if data.nbytes < needed:
        raise CustomMsgError(f"CustomMsg data has {data.nbytes} bytes, its {count} points need {needed}")
    if count == 0:
        return stamp_ns, np.empty((0, 3)), np.empty(0)
    dtype = np.dtype(
        {
            "names": _POINT_NAMES,
            "formats": [order + code for code in _POINT_FORMATS],
            "offsets": _POINT_OFFSETS,
            "itemsize": _POINT_SIZE,
        }
    )
    cloud = np.ndarray((count,), dtype=dtype, buffer=data, offset=start, strides=(stride,))
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    offsets = cloud["offset_time"]
    keep = returns(points, cloud["tag"])
    if keep is not None:
        points, offsets = points[keep], offsets[keep]
    times = relative_seconds(offsets, 0.0)  # uint32 ns after timebase; none when all the same
    return stamp_ns, points, times + (timebase - stamp_ns) * 1e-9 if len(times) else times


def custom_msg_frame_id(raw: bytes | memoryview, cdr: bool) -> str:
    """header.frame_id of one serialized CustomMsg (ROS1, or CDR of either byte order)."""
    data = memoryview(raw).cast("B")
    _, _, length = _header(data, cdr)
    return bytes(data[_FRAME_ID_AT : _FRAME_ID_AT + length]).rstrip(b"\0").decode("utf-8", errors="replace")


def _header(data: memoryview, cdr: bool) -> tuple[str, int, int]:
    """(byte order, header.stamp [ns], length of header.frame_id in bytes) of ROS1 bytes (seq, sec, nsec, then
    frame_id's length) or CDR bytes (a 4-byte encapsulation header whose second byte is 1 for little endian, sec,
    nsec, then frame_id's length, its terminating zero counted): frame_id's text starts at byte `_FRAME_ID_AT` in
    both."""
    order = ("<" if data[1] == 1 else ">") if cdr else "<"
    sec, nsec, length = struct.unpack_from(order + ("iII" if cdr else "III"), data, 4)  # sec: int32 in ROS2
    return order, sec * 1_000_000_000 + nsec, length


def _ros1_layout(data: memoryview) -> tuple[int, int, int, int, str, int]:
    """(stamp ns, timebase ns, point count, offset of the first point, byte order, point stride) of ROS1 bytes:
    header (seq, sec, nsec, frame_id), timebase, point_num, lidar_id, rsvd[3], then the points' length and the
    points, packed."""
    _, stamp_ns, frame_length = _header(data, cdr=False)
    position = _FRAME_ID_AT + frame_length
    timebase, _, _, count = struct.unpack_from("<QIB3xI", data, position)
    return stamp_ns, timebase, count, position + 20, "<", _POINT_SIZE


def _cdr_layout(data: memoryview) -> tuple[int, int, int, int, str, int]:
    """The same for CDR bytes: every value aligned to its own size counted from the end of the 4-byte encapsulation
    header, so a point takes 20 bytes."""
    order, stamp_ns, frame_length = _header(data, cdr=True)
    position = _aligned(_FRAME_ID_AT - 4 + frame_length, 8)  # body offset of timebase
    timebase, _, _, count = struct.unpack_from(order + "QIB3xI", data, 4 + position)
    return stamp_ns, timebase, count, 4 + position + 20, order, _aligned(_POINT_SIZE, 4)


def _aligned(position: int, size: int) -> int:
    return -(-position // size) * size


def encode_custom_msg(
    typestore: Typestore,
    msgtype: str,
    stamp: float,
    points: np.ndarray,
    times: np.ndarray,
    frame_id: str = "livox_frame",
    tags: np.ndarray | None = None,
) -> Any:
    """A CustomMsg of `typestore` (registered with `register_custom_msg`) holding points (N, 3) [m] and times (N,)
    [s] after `stamp` (empty: every offset_time 0), and `tags` (N,) (None: every tag 0); timebase and header.stamp
    are both `stamp`, as Livox's drivers set them."""
    offsets = nanoseconds_after_stamp(times, len(points))
    tags = np.zeros(len(points), dtype=np.uint8) if tags is None else np.asarray(tags, dtype=np.uint8)
    types = typestore.types
    point = types[f"{msgtype.split('/')[0]}/msg/CustomPoint"]
    cloud = np.asarray(points, dtype=np.float32)
    return types[msgtype](
        header=ros_header(typestore, stamp, frame_id),
        timebase=round(stamp * 1e9),
        point_num=len(cloud),
        lidar_id=0,
        rsvd=np.zeros(3, dtype=np.uint8),
        points=[
            point(offset_time=int(t), x=float(x), y=float(y), z=float(z), reflectivity=0, tag=int(tag), line=0)
            for (x, y, z), t, tag in zip(cloud, offsets, tags, strict=True)
        ],
    )
