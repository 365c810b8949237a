"""ROS bags of sensor_msgs/PointCloud2 scans, read and written with rosbags (no ROS installation needed).

Reads ROS1 .bag files, ROS2 bag folders (sqlite3 .db3 or mcap storage) and bare .mcap or .db3 files.
A scan is a tuple (stamp, points, times): stamp = the message's header.stamp [s] (not the record time);
points (N, 3) float64 [m] in the sensor frame; times (N,) float64 [s] per point relative to the stamp, or
an empty array when the cloud carries no per-point time.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from pipelines.atomic_write import atomic_dir, atomic_path

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")
TIME_FIELDS = ("t", "time", "timestamp", "time_offset", "offset_time")  # searched in this order
LAYOUTS = ("compact", "ouster")
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}  # sensor_msgs/PointField
_STORAGE_SUFFIXES = (".mcap", ".db3")
_MAGIC = {".bag": (b"#ROSBAG V2.0\n", "a ROS1 bag"), ".mcap": (b"\x89MCAP0\r\n", "an MCAP file"),
          ".db3": (b"SQLite format 3\x00", "an SQLite database")}


class BagError(ValueError):
    """A bag that cannot be read as asked; the message is one line naming the file (and the topic)."""


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _storage_source(path: Path) -> Path:
    """What to hand AnyReader for `path`: the path itself, or the only storage file of a ROS2 folder that
    lost its metadata.yaml."""
    if not path.exists():
        raise BagError(f"{path}: no such file or folder")
    if path.name == "metadata.yaml":
        path = path.parent
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return path
        storages = [p for p in path.iterdir() if p.suffix in _STORAGE_SUFFIXES]
        if len(storages) == 1:
            return storages[0]
        raise BagError(f"{path}: not a ROS2 bag folder (no metadata.yaml and not exactly one .mcap or .db3 file)")
    if path.suffix not in _MAGIC:
        raise BagError(f"{path}: not a bag (expected a ROS1 .bag file, a ROS2 bag folder, or a .mcap or .db3 file)")
    magic, kind = _MAGIC[path.suffix]
    try:
        with path.open("rb") as file:
            start = file.read(len(magic))
    except OSError as error:
        raise BagError(f"{path}: cannot read it ({error.strerror})") from None
    if start != magic:
        raise BagError(f"{path}: not {kind} (wrong file signature)")
    return path


def _open_reader(path: Path) -> AnyReader:
    """An open AnyReader over `path`."""
    source = _storage_source(path)
    try:
        reader = AnyReader([source], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as error:  # rosbags raises many types on bad files (ReaderError, struct.error, ...)
        raise BagError(f"{path}: corrupt or truncated bag ({_one_line(error)})") from None
    return reader


def _pointcloud_counts(reader: AnyReader) -> dict[str, int]:
    return {name: info.msgcount for name, info in reader.topics.items() if info.msgtype == POINTCLOUD2}


def _listing(counts: dict[str, int]) -> str:
    return ", ".join(f"{name} ({count} message{'s' * (count != 1)})" for name, count in counts.items())


def pointcloud_topics(path: str | Path) -> dict[str, int]:
    """The sensor_msgs/PointCloud2 topics of a bag and their message counts; BagError if it is unreadable."""
    reader = _open_reader(Path(path))
    try:
        return _pointcloud_counts(reader)
    finally:
        reader.close()


def _choose_topic(path: Path, reader: AnyReader, topic: str | None) -> str:
    clouds = _pointcloud_counts(reader)
    if topic is None:
        if not clouds:
            others = ", ".join(f"{name} ({info.msgtype})" for name, info in reader.topics.items()) or "none"
            raise BagError(f"{path}: no sensor_msgs/PointCloud2 topic (topics: {others})")
        if len(clouds) > 1:
            raise BagError(f"{path}: several PointCloud2 topics, choose one with --topic: {_listing(clouds)}")
        return next(iter(clouds))
    if topic not in clouds:
        known = reader.topics.get(topic)
        what = "is not in the bag" if known is None else f"is a {known.msgtype} topic, not PointCloud2"
        raise BagError(f"{path}: topic {topic} {what}; PointCloud2 topics: {_listing(clouds) or 'none'}")
    return topic


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class BagScans:
    """The scans of one PointCloud2 topic of a bag, streamed one message at a time.

    `BagScans(path, topic=None)` opens the bag (topic None: its only PointCloud2 topic) and raises BagError
    when it cannot. Attributes: `path`, `topic`, `count` (messages), `duration` (last minus first
    header.stamp [s], of the first and last recorded messages). Iterating yields (stamp, points, times)
    (see the module docstring), in record order, again from the start at each iteration; messages with no
    points yield points of shape (0, 3). Use as a context manager, or call `close()`.
    """

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        self.path = Path(path)
        self._reader: AnyReader | None = _open_reader(self.path)
        try:
            self.topic = _choose_topic(self.path, self._reader, topic)
            self._connections = [c for c in self._reader.connections if c.topic == self.topic]
            self.count = _pointcloud_counts(self._reader)[self.topic]
            self.duration = self._duration()
        except BaseException:
            self.close()
            raise

    def __len__(self) -> int:
        return self.count

    def __enter__(self) -> BagScans:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the bag (idempotent)."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def _open(self) -> AnyReader:
        if self._reader is None:
            raise BagError(f"{self.path}: the bag is closed")
        return self._reader

    def _raw_messages(self, start: int | None = None) -> Iterator[tuple[Any, bytes]]:
        """(connection, serialized message) of the topic recorded at or after `start` [ns]; rosbags' errors
        become BagError."""
        messages = self._open().messages(self._connections, start=start)
        while True:
            try:
                item = next(messages, None)
            except Exception as error:  # corrupt or truncated data: rosbags raises many types
                raise BagError(f"{self.path}: corrupt or truncated bag ({_one_line(error)})") from None
            if item is None:
                return
            yield item[0], item[2]

    def _deserialize(self, connection: Any, raw: bytes, index: int | str) -> Any:
        try:
            return self._open().deserialize(raw, connection.msgtype)
        except Exception as error:
            raise BagError(f"{self.path}: {self.topic} message {index}: cannot deserialize ({_one_line(error)})"
                           ) from None

    def _duration(self) -> float:
        """Header stamp of the last recorded message minus that of the first [s]; found by reading a growing
        window at the end of the bag, so a long bag is not read whole."""
        messages = self._raw_messages()
        first = next(messages, None)
        messages.close()
        if first is None:
            return 0.0
        reader = self._open()
        start, end = reader.start_time, reader.end_time
        window = 2 * max(1, (end - start) // max(self.count, 1))
        while True:
            last = None
            for last in self._raw_messages(max(start, end - window)):
                pass
            if last is not None or end - window <= start:
                break
            window *= 8
        if last is None:
            return 0.0
        stamps = [_stamp_ns(self._deserialize(c, raw, label)) for (c, raw), label in ((first, 0), (last, "last"))]
        return (stamps[1] - stamps[0]) * 1e-9

    def __iter__(self) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
        for index, (connection, raw) in enumerate(self._raw_messages()):
            msg = self._deserialize(connection, raw, index)
            try:
                points, times = pointcloud2_arrays(msg)
            except BagError as error:
                raise BagError(f"{self.path}: {self.topic} message {index}: {error}") from None
            yield msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, points, times


def pointcloud2_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float64 [m], times (N,) float64 [s] relative to header.stamp, or empty) of a PointCloud2.

    Any layout: x, y, z of any numeric datatype, any point_step, padding and extra fields, row_step beyond
    width * point_step, organized clouds (height > 1), either byte order. Decoded through a strided numpy
    view of `data`, without a loop over points. Points that are not finite (is_dense false) or exactly at
    the origin (the no-return points of Ouster drivers) are dropped, with their times.

    Per-point time: the first field named t, time, timestamp, time_offset or offset_time, of any datatype.
      - Unit: integer fields are nanoseconds (Ouster `t` uint32, Livox `offset_time` uint32); float fields
        are seconds (Velodyne `time` float32, Hesai/Robosense `timestamp` float64), unless their typical
        magnitude exceeds 1e12: then nanoseconds (the float64 `timestamp` of Livox's driver2 PointCloud2).
      - Reference: the values are absolute times when their median is beyond 1 s and closer to the header
        stamp than to zero (the stamp is then subtracted); relative to the stamp otherwise.
      - A field with the same value at every point (or any non-finite value) carries no time: empty array.

    Raises:
        BagError: no x, y or z field, an unknown datatype, a field beyond point_step, or too little data.
    """
    fields = {field.name: field for field in msg.fields}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise BagError(f"PointCloud2 without {'/'.join(missing)} field (fields: {', '.join(fields) or 'none'})")
    time_name = next((name for name in TIME_FIELDS if name in fields), None)
    names = ["x", "y", "z"] + ([time_name] if time_name else [])
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for name in names:
        code = _DATATYPES.get(fields[name].datatype)
        if code is None:
            raise BagError(f"PointCloud2 field {name} has an unknown datatype {fields[name].datatype}")
        if fields[name].offset + int(code[1]) > msg.point_step:
            raise BagError(f"PointCloud2 field {name} at offset {fields[name].offset} exceeds point_step "
                           f"{msg.point_step}")
        formats.append(order + code)
    height, width, point_step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if height * width == 0:
        return np.empty((0, 3)), np.empty(0)
    if row_step < width * point_step:
        raise BagError(f"PointCloud2 row_step {row_step} < width {width} x point_step {point_step}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        raise BagError(f"PointCloud2 data has {data.size} bytes, {height}x{width} points need {needed}")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": [fields[n].offset for n in names],
                      "itemsize": point_step})
    cloud = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    points = np.empty((height, width, 3))
    for k, axis in enumerate("xyz"):
        points[..., k] = cloud[axis]
    points = points.reshape(-1, 3)
    squared_range = np.einsum("ij,ij->i", points, points)  # NaN or inf unless x, y and z are all finite
    valid = (squared_range > 0.0) & (squared_range < np.inf)
    keep = None if valid.all() else valid
    if keep is not None:
        points = points[keep]
    if time_name is None:
        return points, np.empty(0)
    values = cloud[time_name].reshape(-1)
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return points, _relative_seconds(values if keep is None else values[keep], stamp)


def _relative_seconds(values: np.ndarray, stamp: float) -> np.ndarray:
    """Per-point times [s] relative to `stamp` [s] from a raw time field (rules: `pointcloud2_arrays`)."""
    if values.size == 0 or not np.isfinite(values).all():
        return np.empty(0)
    typical = float(np.median(values[:: max(1, values.size // 256)]))
    scale = 1e-9 if values.dtype.kind in "iu" or abs(typical) > 1e12 else 1.0
    times = values.astype(np.float64) * scale
    if abs(typical * scale) > 1.0 and abs(typical * scale - stamp) < abs(typical * scale):
        times -= stamp  # absolute times
    if times.min() == times.max():
        return np.empty(0)
    return times


def encode_pointcloud2(typestore: Typestore, stamp: float, cloud: np.ndarray, frame_id: str = "lidar",
                       row_step: int | None = None) -> Any:
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
        fields.append(types["sensor_msgs/msg/PointField"](name=name, offset=offset,
                                                          datatype=codes[dtype.kind + str(dtype.itemsize)], count=1))
        big = big or dtype.byteorder == ">"
    rows = np.zeros((height, row_step), dtype=np.uint8)
    rows[:, : width * point_step] = np.ascontiguousarray(cloud).view(np.uint8).reshape(height, -1)
    sec, nanosec = divmod(round(stamp * 1e9), 1_000_000_000)
    header_fields = {"stamp": types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), "frame_id": frame_id}
    if "seq" in types["std_msgs/msg/Header"].__dataclass_fields__:  # ROS1
        header_fields["seq"] = 0
    return types[POINTCLOUD2](
        header=types["std_msgs/msg/Header"](**header_fields), height=height, width=width, fields=fields,
        is_bigendian=big, point_step=point_step, row_step=row_step, data=rows.reshape(-1),
        is_dense=all(np.isfinite(cloud[a]).all() for a in "xyz" if a in cloud.dtype.names),
    )


def scan_cloud(points: np.ndarray, times: np.ndarray, intensities: np.ndarray | None = None,
               layout: str = "compact") -> np.ndarray:
    """The structured array write_bag stores for one scan.

    compact: x, y, z float32, then intensity float32 when given, then t uint32 [ns] when times are given,
    packed. ouster: the ouster-ros default point (x, y, z float32; intensity float32 at 16; t uint32 [ns]
    at 20; reflectivity, ring, ambient uint16; range uint32 [mm]; point_step 48), zeros where unknown.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose from {', '.join(LAYOUTS)}")
    has_times = len(times) > 0
    if has_times and (len(times) != len(points) or times.min() < 0 or times.max() >= 2**32 * 1e-9):
        raise ValueError("times must be one per point, within [0, 4.29) s of the stamp")
    if layout == "ouster":
        dtype = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                          "formats": ["<f4"] * 4 + ["<u4"] + ["<u2"] * 3 + ["<u4"],
                          "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
    else:
        names = ["x", "y", "z"] + ["intensity"] * (intensities is not None) + ["t"] * has_times
        dtype = np.dtype([(name, "<u4" if name == "t" else "<f4") for name in names])
    cloud = np.zeros(len(points), dtype=dtype)
    for k, axis in enumerate("xyz"):
        cloud[axis] = points[:, k]
    if intensities is not None:
        cloud["intensity"] = intensities
    if has_times:
        cloud["t"] = np.round(times * 1e9)
    if layout == "ouster":
        cloud["range"] = np.round(np.linalg.norm(points, axis=1) * 1000.0)
    return cloud


Scan = tuple  # (stamp [s], points (N, 3) [m], times (N,) [s] or empty[, intensities (N,)])


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


def write_bag(path: str | Path, fmt: str, scans: Iterable[Scan], topic: str = "/points", frame_id: str = "lidar",
              layout: str = "compact", overwrite: bool = False) -> int:
    """Write scans as sensor_msgs/PointCloud2 messages into a new bag; returns the number of messages.

    Args:
        path: a .bag file for fmt "ros1"; a bag folder (not ending in .bag) for "ros2-sqlite3"/"ros2-mcap".
        scans: (stamp [s], points (N, 3) [m], times (N,) [s] relative to the stamp or empty[, intensities]),
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


def _write_scans(writer: Writer1 | Writer2, connection: Any, typestore: Typestore, serialize: Any,
                 scans: Iterable[Scan], frame_id: str, layout: str) -> int:
    count = 0
    for stamp, points, times, *rest in scans:
        times = np.asarray(times, dtype=np.float64)
        cloud = scan_cloud(np.asarray(points), times, rest[0] if rest else None, layout)
        msg = encode_pointcloud2(typestore, stamp, cloud, frame_id)
        end = stamp + (float(times.max()) if len(times) else 0.0)
        writer.write(connection, round(end * 1e9), serialize(msg, POINTCLOUD2))
        count += 1
    return count

