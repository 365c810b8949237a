"""Reading the LiDAR scans of ROS bags with rosbags (no ROS installation needed): sensor_msgs/PointCloud2 and
Livox CustomMsg messages.

Reads ROS1 .bag files, ROS2 bag folders (sqlite3 .db3 or mcap storage) and bare .mcap or .db3 files. Each
message becomes a `Scan`: timestamp = its header.stamp [s] (not the record time, unless header.stamp never
changes: `BagScans.stamps`); points (N, 3) float64 [m] in the sensor frame; times (N,) float64 [s] per point
relative to header.stamp, or an empty array when the cloud carries no per-point time.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pipelines.io.bags.livox import CUSTOM_MSG_TYPES, CustomMsgError, custom_msg_arrays, custom_msg_frame_id
from pipelines.io.bags.pointcloud2 import POINTCLOUD2, PointCloud2Error, pointcloud2_arrays
from sandro_slam.scan import Scan

SCAN_TYPES = (POINTCLOUD2, *CUSTOM_MSG_TYPES)
_STORAGE_SUFFIXES = (".mcap", ".db3")
_MAGIC = {
    ".bag": (b"#ROSBAG V2.0\n", "a ROS1 bag"),
    ".mcap": (b"\x89MCAP0\r\n", "an MCAP file"),
    ".db3": (b"SQLite format 3\x00", "an SQLite database"),
}


class BagError(ValueError):
    """A bag that cannot be read as asked; the message is one line naming the file (and the topic)."""


def one_line(error: BaseException) -> str:
    """An error's message on one line of at most 200 characters."""
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


def open_reader(path: Path) -> AnyReader:
    """An open AnyReader over the bag at `path`; BagError naming it if it cannot be opened."""
    source = _storage_source(path)
    try:
        reader = AnyReader([source], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as error:  # rosbags raises many types on bad files (ReaderError, struct.error, ...)
        raise BagError(f"{path}: corrupt or truncated bag ({one_line(error)})") from None
    return reader


def _scan_counts(reader: AnyReader) -> dict[str, int]:
    return {name: info.msgcount for name, info in reader.topics.items() if info.msgtype in SCAN_TYPES}


def _listing(counts: dict[str, int]) -> str:
    return ", ".join(f"{name} ({count} message{'s' * (count != 1)})" for name, count in counts.items())


def pointcloud_topics(path: str | Path) -> dict[str, int]:
    """The point cloud topics (PointCloud2 or Livox CustomMsg) of a bag and their message counts; BagError if it
    is unreadable."""
    reader = open_reader(Path(path))
    try:
        return _scan_counts(reader)
    finally:
        reader.close()


def _choose_topic(path: Path, reader: AnyReader, topic: str | None) -> str:
    clouds = _scan_counts(reader)
    if topic is None:
        if not clouds:
            others = ", ".join(f"{name} ({info.msgtype})" for name, info in reader.topics.items()) or "none"
            raise BagError(f"{path}: no sensor_msgs/PointCloud2 or Livox CustomMsg topic (topics: {others})")
        if len(clouds) > 1:
            raise BagError(f"{path}: several point cloud topics, choose one with --topic: {_listing(clouds)}")
        return next(iter(clouds))
    if topic not in clouds:
        known = reader.topics.get(topic)
        what = "is not in the bag" if known is None else f"is a {known.msgtype} topic, not a point cloud"
        raise BagError(f"{path}: topic {topic} {what}; point cloud topics: {_listing(clouds) or 'none'}")
    return topic


class BagScans:
    """The scans of one point cloud topic (PointCloud2 or Livox CustomMsg) of a bag, streamed one message at a time.

    `BagScans(path, topic=None)` opens the bag (topic None: its only point cloud topic) and raises BagError
    when it cannot. Attributes: `path`, `topic`, `count` (messages), `topic_types` ({topic: message type} of every
    topic of the bag that holds messages), `stamps` ("header", or "record" when the
    first and last messages carry the same header.stamp, as drivers that leave it zero do: each scan's stamp is
    then the time it was recorded), `duration` (last minus first stamp [s], of the first and last recorded
    messages). Iterating yields (stamp, points, times) (see the module docstring), in record order, again from
    the start at each iteration; messages with no points yield points of shape (0, 3). Use as a context manager,
    or call `close()`.
    """

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        self.path = Path(path)
        self._reader: AnyReader | None = open_reader(self.path)
        try:
            self.topic = _choose_topic(self.path, self._reader, topic)
            self._connections = [c for c in self._reader.connections if c.topic == self.topic]
            self.count = _scan_counts(self._reader)[self.topic]
            self.topic_types = {name: info.msgtype for name, info in self._reader.topics.items() if info.msgcount}
            self._custom_msg = self._reader.topics[self.topic].msgtype in CUSTOM_MSG_TYPES
            self.stamps, self.duration = self._stamps_and_duration()
        except BaseException:
            self.close()
            raise

    def __len__(self) -> int:
        return self.count

    def __enter__(self) -> BagScans:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
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

    def _raw_messages(self, start: int | None = None) -> Iterator[tuple[Any, int, bytes]]:
        """(connection, record time [ns], serialized message) of the topic recorded at or after `start` [ns];
        rosbags' errors become BagError."""
        messages = self._open().messages(self._connections, start=start)
        while True:
            try:
                item = next(messages, None)
            except Exception as error:  # corrupt or truncated data: rosbags raises many types
                raise BagError(f"{self.path}: corrupt or truncated bag ({one_line(error)})") from None
            if item is None:
                return
            yield item

    def frame_id(self) -> str:
        """header.frame_id of the topic's first message: the frame its points are in; BagError on a bag that cannot
        be read or a message that cannot be deserialized."""
        messages = self._raw_messages()
        first = next(messages, None)
        messages.close()
        if first is None:
            raise BagError(f"{self.path}: {self.topic} holds no message")
        connection, _, raw = first
        if self._custom_msg:
            return custom_msg_frame_id(raw, cdr=self._open().is2)
        try:
            return str(self._open().deserialize(raw, connection.msgtype).header.frame_id)
        except Exception as error:
            raise BagError(f"{self.path}: {self.topic} message 0: cannot deserialize ({one_line(error)})") from None

    def _decode(self, connection: Any, raw: bytes, index: int | str) -> tuple[int, np.ndarray, np.ndarray]:
        """(header.stamp [ns], points, times) of one serialized message; BagError naming it if it cannot be."""
        where = f"{self.path}: {self.topic} message {index}"
        if self._custom_msg:
            try:
                return custom_msg_arrays(raw, cdr=self._open().is2)
            except CustomMsgError as error:
                raise BagError(f"{where}: {error}") from None
        try:
            msg = self._open().deserialize(raw, connection.msgtype)
        except Exception as error:
            raise BagError(f"{where}: cannot deserialize ({one_line(error)})") from None
        try:
            points, times = pointcloud2_arrays(msg)
        except PointCloud2Error as error:
            raise BagError(f"{where}: {error}") from None
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec), points, times

    def _stamps_and_duration(self) -> tuple[str, float]:
        """(`stamps`, the stamp of the last recorded message minus that of the first [s]); the last found by
        reading a growing window at the end of the bag, so a long bag is not read whole."""
        messages = self._raw_messages()
        first = next(messages, None)
        messages.close()
        if first is None:
            return "header", 0.0
        reader = self._open()
        start, end = reader.start_time, reader.end_time
        window = 2 * max(1, (end - start) // max(self.count, 1))
        while True:
            last = next(iter(deque(self._raw_messages(max(start, end - window)), maxlen=1)), None)
            if last is not None or end - window <= start:
                break
            window *= 8
        if last is None:
            return "header", 0.0
        stamps = [self._decode(c, raw, label)[0] for (c, _, raw), label in ((first, 0), (last, "last"))]
        if stamps[0] == stamps[1] and self.count > 1:
            return "record", (last[1] - first[1]) * 1e-9
        return "header", (stamps[1] - stamps[0]) * 1e-9

    def __iter__(self) -> Iterator[Scan]:
        for index, (connection, recorded, raw) in enumerate(self._raw_messages()):
            stamp_ns, points, times = self._decode(connection, raw, index)
            if self.stamps == "record":
                stamp_ns = recorded
            seconds, nanoseconds = divmod(stamp_ns, 1_000_000_000)
            yield Scan(seconds + nanoseconds * 1e-9, points, times)
