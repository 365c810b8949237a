"""sensor_msgs/PointCloud2 to and from numpy: decoding any point layout, encoding structured arrays."""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from pipelines.io.lidar_points import (
    carries_livox_tags,
    nanoseconds_after_stamp,
    relative_seconds,
    returns,
    time_field,
)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
LAYOUTS = ("compact", "ouster")
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}  # sensor_msgs/PointField


class PointCloud2Error(ValueError):
    """A PointCloud2 message whose points cannot be decoded; the message says why in one line."""


def pointcloud2_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float64 [m], times (N,) float64 [s] relative to header.stamp, or empty) of a PointCloud2.

    Any layout: x, y, z of any numeric datatype, any point_step, padding and extra fields, row_step beyond
    width * point_step, organized clouds (height > 1), either byte order. Decoded through a strided numpy
    view of `data`, without a loop over points. Points that are not finite (is_dense false), exactly at the
    origin (the no-return points of Ouster drivers) or tagged as noise by a Livox sensor
    (`lidar_points.carries_livox_tags`, `lidar_points.livox_noise`) are dropped, with their times.

    Per-point time: the first field named t, time, timestamp, time_offset or offset_time, of any datatype, read
    by the rules of `lidar_points.relative_seconds` (unit and reference from the values themselves).

    Raises:
        PointCloud2Error: no x, y or z field, an unknown datatype, a field beyond point_step, or too little data.
    """
    fields = {field.name: field for field in msg.fields}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise PointCloud2Error(f"PointCloud2 without {'/'.join(missing)} field (fields: {', '.join(fields) or 'none'})")
    time_name = time_field(fields)
    livox = carries_livox_tags(fields, "tag" in fields and fields["tag"].datatype == 2)  # 2: uint8
    names = ["x", "y", "z"] + ([time_name] if time_name else []) + (["tag"] if livox else [])
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for name in names:
        code = _DATATYPES.get(fields[name].datatype)
        if code is None:
            raise PointCloud2Error(f"PointCloud2 field {name} has an unknown datatype {fields[name].datatype}")
        if fields[name].offset + int(code[1]) > msg.point_step:
            raise PointCloud2Error(
                f"PointCloud2 field {name} at offset {fields[name].offset} exceeds point_step {msg.point_step}"
            )
        formats.append(order + code)
    height, width, point_step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if height * width == 0:
        return np.empty((0, 3)), np.empty(0)
    if row_step < width * point_step:
        raise PointCloud2Error(f"PointCloud2 row_step {row_step} < width {width} x point_step {point_step}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        raise PointCloud2Error(f"PointCloud2 data has {data.size} bytes, {height}x{width} points need {needed}")
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": [fields[n].offset for n in names], "itemsize": point_step}
    )
    cloud = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    points = np.empty((height, width, 3))
    for k, axis in enumerate("xyz"):
        points[..., k] = cloud[axis]
    points = points.reshape(-1, 3)
    keep = returns(points, cloud["tag"].reshape(-1) if livox else None)
    if keep is not None:
        points = points[keep]
    if time_name is None:
        return points, np.empty(0)
    values = cloud[time_name].reshape(-1)
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return points, relative_seconds(values if keep is None else values[keep], stamp)


def encode_pointcloud2(
    typestore: Typestore, stamp: float, cloud: np.ndarray, frame_id: str = "lidar", row_step: int | None = None
) -> Any:
    """A sensor_msgs/PointCloud2 of `typestore` holding a structured array `cloud` ((N,) or organized (H, W))
    byte for byte: its field names, datatypes, offsets, itemsize (point_step) and byte order. `row_step`
    (default W * itemsize) larger than that pads each row. `stamp` [s] goes into header.stamp."""
    types = typestore.types
    height, width = (1, cloud.shape[0]) if cloud.ndim == 1 else cloud.shape
    point_step = cloud.dtype.itemsize
    row_step = width * point_step if row_step is None else row_step
    codes = {code: datatype for datatype, code in _DATATYPES.items()}
    fields, big = [], False
    for name, (dtype, offset, *_) in cloud.dtype.fields.items():
        fields.append(
            types["sensor_msgs/msg/PointField"](
                name=name, offset=offset, datatype=codes[dtype.kind + str(dtype.itemsize)], count=1
            )
        )
        big = big or dtype.byteorder == ">"
    rows = np.zeros((height, row_step), dtype=np.uint8)
    rows[:, : width * point_step] = np.ascontiguousarray(cloud).view(np.uint8).reshape(height, -1)
    return types[POINTCLOUD2](
        header=ros_header(typestore, stamp, frame_id),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big,
        point_step=point_step,
        row_step=row_step,
        data=rows.reshape(-1),
        is_dense=all(np.isfinite(cloud[a]).all() for a in "xyz" if a in cloud.dtype.names),
    )


def ros_header(typestore: Typestore, stamp: float, frame_id: str) -> Any:
    """A std_msgs/Header of `typestore` (ROS1's with seq 0, or ROS2's) stamped `stamp` [s]."""
    types = typestore.types
    sec, nanosec = divmod(round(stamp * 1e9), 1_000_000_000)
    fields = {"stamp": types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), "frame_id": frame_id}
    if "seq" in types["std_msgs/msg/Header"].__dataclass_fields__:  # ROS1
        fields["seq"] = 0
    return types["std_msgs/msg/Header"](**fields)


def scan_cloud(points: np.ndarray, times: np.ndarray, layout: str = "compact") -> np.ndarray:
    """The structured array write_bag stores for one scan.

    compact: x, y, z float32, then t uint32 [ns] when times are given, packed.
    ouster: the ouster-ros default point (x, y, z float32; intensity float32 at 16; t uint32 [ns] at 20;
    reflectivity, ring, ambient uint16; range uint32 [mm]; point_step 48), zeros where unknown.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose from {', '.join(LAYOUTS)}")
    has_times = len(times) > 0
    nanoseconds = nanoseconds_after_stamp(times, len(points))
    if layout == "ouster":
        dtype = np.dtype(
            {
                "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                "formats": ["<f4"] * 4 + ["<u4"] + ["<u2"] * 3 + ["<u4"],
                "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
                "itemsize": 48,
            }
        )
    else:
        names = ["x", "y", "z"] + ["t"] * has_times
        dtype = np.dtype([(name, "<u4" if name == "t" else "<f4") for name in names])
    cloud = np.zeros(len(points), dtype=dtype)
    for k, axis in enumerate("xyz"):
        cloud[axis] = points[:, k]
    if has_times:
        cloud["t"] = nanoseconds
    if layout == "ouster":
        cloud["range"] = np.round(np.linalg.norm(points, axis=1) * 1000.0)
    return cloud
