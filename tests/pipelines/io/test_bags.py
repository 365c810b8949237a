"""ROS bag reading and writing (pipelines.bag_io) and the `sandro-simulate` command."""

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from pipelines.io.bags import FORMATS, BagError, BagScans, pointcloud_topics, write_bag
from pipelines.io.bags.pointcloud2 import (
    POINTCLOUD2,
    PointCloud2Error,
    encode_pointcloud2,
    pointcloud2_arrays,
    scan_cloud,
)
from pipelines.io.inputs import open_input
from pipelines.simulation import simulate_sequence

ROS2 = get_typestore(Stores.LATEST)
ROS1 = get_typestore(Stores.ROS1_NOETIC)
STAMP = 1_700_000_123.25  # [s], exactly representable in ns


def bag_name(fmt: str) -> str:
    return "scans.bag" if fmt == "ros1" else f"scans_{fmt}"


def cloud_of(fields: list[tuple[str, str, int]], itemsize: int, values: dict[str, np.ndarray]) -> np.ndarray:
    """A structured array with fields (name, numpy type, offset) of `itemsize` bytes each, filled from `values`."""
    names, formats, offsets = zip(*fields)
    dtype = np.dtype({"names": list(names), "formats": list(formats), "offsets": list(offsets), "itemsize": itemsize})
    cloud = np.zeros(len(next(iter(values.values()))), dtype=dtype)
    for name, value in values.items():
        cloud[name] = value
    return cloud


def xyz(n: int = 100, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-50.0, 50.0, (n, 3)).astype(np.float32).astype(np.float64)


def decode(cloud: np.ndarray, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    return pointcloud2_arrays(encode_pointcloud2(ROS2, STAMP, cloud, **kwargs))


def test_float32_packed_without_time():
    p = xyz()
    fields = [("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8)]
    cloud = cloud_of(fields, 12, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]})
    points, times = decode(cloud)
    np.testing.assert_array_equal(points, p)
    assert points.dtype == np.float64 and times.shape == (0,)


def test_float64_with_padding_and_extra_fields_in_any_order():
    p = np.random.default_rng(1).normal(size=(50, 3)) * 20
    fields = [("intensity", "<f4", 0), ("z", "<f8", 8), ("ring", "<u2", 16), ("x", "<f8", 24), ("y", "<f8", 40)]
    cloud = cloud_of(fields, 56, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "intensity": 7.0, "ring": 3})
    points, _ = decode(cloud)
    np.testing.assert_array_equal(points, p)


def test_velodyne_unaligned_float_time_in_relative_seconds():
    p, t = xyz(), np.linspace(0.0, 0.099, 100)
    fields = [
        ("x", "<f4", 0),
        ("y", "<f4", 4),
        ("z", "<f4", 8),
        ("intensity", "<f4", 12),
        ("ring", "<u2", 16),
        ("time", "<f4", 18),
    ]
    cloud = cloud_of(fields, 22, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "time": t})
    points, times = decode(cloud)
    np.testing.assert_array_equal(points, p)
    np.testing.assert_allclose(times, t, atol=1e-8)


def test_ouster_layout_uint32_nanoseconds():
    p, t = xyz(), np.linspace(0.0, 0.099, 100)
    cloud = scan_cloud(p, t, layout="ouster")
    assert cloud.dtype.itemsize == 48 and cloud.dtype.fields["t"][1] == 20
    points, times = decode(cloud)
    np.testing.assert_array_equal(points, p)
    np.testing.assert_allclose(times, t, atol=1e-9)


@pytest.mark.parametrize(
    ("name", "numpy_type", "scale", "absolute"),
    [
        ("timestamp", "<f8", 1.0, True),  # Hesai, Robosense: absolute seconds
        ("timestamp", "<f8", 1e9, True),  # Livox driver2 PointCloud2: absolute nanoseconds as a double
        ("time", "<f8", 1.0, False),  # Leishen: relative seconds as a double
        ("offset_time", "<u4", 1e9, False),  # Livox: nanoseconds after the stamp
        ("time_offset", "<i4", 1e9, False),
        ("t", "<f4", 1.0, False),
    ],
)
def test_time_fields_units_and_reference(name, numpy_type, scale, absolute):
    p, t = xyz(), np.linspace(0.0, 0.099, 100)
    raw = ((STAMP if absolute else 0.0) + t) * scale
    if numpy_type[1] in "ui":
        raw = np.round((STAMP * 10**9 if absolute else 0) + np.round(t * 1e9)).astype(numpy_type)
    fields = [("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), (name, numpy_type, 16)]
    cloud = cloud_of(fields, 24, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], name: raw})
    _, times = decode(cloud)
    np.testing.assert_allclose(times, t, atol=1e-6)


def test_big_endian():
    p, t = xyz(), np.linspace(0.0, 0.099, 100)
    fields = [("x", ">f4", 0), ("y", ">f4", 4), ("z", ">f4", 8), ("t", ">u4", 12)]
    cloud = cloud_of(fields, 16, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "t": np.round(t * 1e9)})
    msg = encode_pointcloud2(ROS2, STAMP, cloud)
    assert msg.is_bigendian
    points, times = pointcloud2_arrays(msg)
    np.testing.assert_array_equal(points, p)
    np.testing.assert_allclose(times, t, atol=1e-9)


def test_organized_cloud_with_row_padding_nan_and_zero_points():
    p, t = xyz(64 * 8).reshape(8, 64, 3), np.linspace(0.0, 0.099, 64 * 8).reshape(8, 64)
    p[2, 5] = np.nan
    p[3, 7] = [np.inf, 0.0, 0.0]
    p[4, 9] = 0.0  # Ouster no-return point
    fields = [("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("t", "<u4", 12)]
    cloud = np.zeros((8, 64), dtype=cloud_of(fields, 32, {"x": [0.0]}).dtype)
    for k, axis in enumerate("xyz"):
        cloud[axis] = p[..., k]
    cloud["t"] = np.round(t * 1e9)
    msg = encode_pointcloud2(ROS2, STAMP, cloud, row_step=64 * 32 + 24)
    assert (msg.height, msg.width, msg.row_step) == (8, 64, 64 * 32 + 24) and not msg.is_dense
    points, times = pointcloud2_arrays(msg)
    keep = np.ones((8, 64), dtype=bool)
    keep[2, 5] = keep[3, 7] = keep[4, 9] = False
    np.testing.assert_array_equal(points, p[keep])
    np.testing.assert_allclose(times, t[keep], atol=1e-9)


def test_empty_message_and_constant_times():
    points, times = decode(scan_cloud(np.empty((0, 3)), np.empty(0)))
    assert points.shape == (0, 3) and times.shape == (0,)
    _, times = decode(scan_cloud(xyz(), np.zeros(100), layout="ouster"))  # t all zero: no time information
    assert times.shape == (0,)


def test_malformed_messages():
    p = xyz()
    no_z = cloud_of([("x", "<f4", 0), ("y", "<f4", 4)], 8, {"x": p[:, 0]})
    with pytest.raises(PointCloud2Error, match="without z field"):
        decode(no_z)
    msg = encode_pointcloud2(ROS2, STAMP, scan_cloud(p, np.empty(0)))
    msg.data = msg.data[:-5]
    with pytest.raises(PointCloud2Error, match="bytes"):
        pointcloud2_arrays(msg)


@pytest.fixture(scope="module")
def frames() -> list[tuple[float, np.ndarray, np.ndarray]]:
    sequence = simulate_sequence(seed=1, frames=3)
    return [(STAMP + f.timestamp, f.points, f.times) for f in sequence.frames()]


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip(tmp_path, frames, fmt):
    path = tmp_path / bag_name(fmt)
    assert write_bag(path, fmt, iter(frames), topic="/lidar") == 3
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary left over
    with BagScans(path) as bag:
        assert (bag.topic, bag.count, len(bag)) == ("/lidar", 3, 3)
        assert bag.duration == pytest.approx(0.2, abs=1e-6)
        for _ in range(2):  # iterating twice starts over
            read = list(bag)
            assert len(read) == 3
        for (stamp, points, times), (stamp0, points0, times0) in zip(read, frames):
            assert stamp == pytest.approx(stamp0, abs=1e-6)
            np.testing.assert_array_equal(points, points0.astype(np.float32))
            np.testing.assert_allclose(times, times0, atol=1e-9)
    with pytest.raises(BagError, match="closed"):
        next(iter(bag))
    with AnyReader([path]) as reader:  # the record time is the sweep end, not header.stamp
        record = [t * 1e-9 for _, t, _ in reader.messages()]
    assert record[0] == pytest.approx(frames[0][0] + frames[0][2].max(), abs=1e-6)


def test_bare_mcap_file_and_folder_without_metadata(tmp_path, frames):
    write_bag(tmp_path / "b", "ros2-mcap", frames[:1])
    assert pointcloud_topics(tmp_path / "b" / "b.mcap") == {"/points": 1}
    (tmp_path / "b" / "metadata.yaml").unlink()
    with BagScans(tmp_path / "b") as bag:
        assert len(list(bag)) == 1


def test_writing_is_atomic(tmp_path, frames):
    def failing():
        yield frames[0]
        raise KeyboardInterrupt

    for fmt in FORMATS:
        with pytest.raises(KeyboardInterrupt):
            write_bag(tmp_path / bag_name(fmt), fmt, failing())
    assert list(tmp_path.iterdir()) == []
    write_bag(tmp_path / "a.bag", "ros1", frames[:1])
    with pytest.raises(FileExistsError):
        write_bag(tmp_path / "a.bag", "ros1", frames)
    write_bag(tmp_path / "a.bag", "ros1", frames, overwrite=True)
    assert BagScans(tmp_path / "a.bag").count == 3


def test_a_bag_whose_header_stamps_do_not_change_is_timed_by_record_time(tmp_path, frames):
    raw = ROS1.serialize_ros1(encode_pointcloud2(ROS1, 0.0, scan_cloud(frames[0][1], frames[0][2])), POINTCLOUD2)
    with Writer1(tmp_path / "zero.bag") as writer:
        connection = writer.add_connection("/points", POINTCLOUD2, typestore=ROS1)
        for k in range(3):
            writer.write(connection, 1_700_000_000_000_000_000 + k * 100_000_000, raw)  # header.stamp 0 in each
    with BagScans(tmp_path / "zero.bag") as bag:
        assert bag.stamps == "record" and bag.duration == pytest.approx(0.2)
        assert [scan.timestamp for scan in bag] == pytest.approx([1.7e9, 1.7e9 + 0.1, 1.7e9 + 0.2], abs=1e-6)
    write_bag(tmp_path / "good.bag", "ros1", frames)
    assert BagScans(tmp_path / "good.bag").stamps == "header"
    source = open_input(tmp_path / "zero.bag")
    assert source.description["stamps"] == "record" and "timed when recorded" in source.notes[0]
    source.scans.close()


@pytest.fixture(scope="module")
def topics_bag(tmp_path_factory, frames) -> Path:
    """A ROS1 bag with PointCloud2 topics /a (2 messages) and /b (1) and a String topic /s."""
    path = tmp_path_factory.mktemp("topics") / "topics.bag"
    raw = ROS1.serialize_ros1(encode_pointcloud2(ROS1, STAMP, scan_cloud(frames[0][1], frames[0][2])), POINTCLOUD2)
    with Writer1(path) as writer:
        a, b = (writer.add_connection(t, POINTCLOUD2, typestore=ROS1) for t in ("/a", "/b"))
        s = writer.add_connection("/s", "std_msgs/msg/String", typestore=ROS1)
        for time, connection in ((1, a), (2, b), (3, a)):
            writer.write(connection, time, raw)
        writer.write(s, 4, ROS1.serialize_ros1(ROS1.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    return path


def test_topic_selection(topics_bag):
    assert pointcloud_topics(topics_bag) == {"/a": 2, "/b": 1}
    with BagScans(topics_bag, "/b") as bag:
        assert bag.count == 1 and len(list(bag)) == 1
    with pytest.raises(BagError, match=r"several point cloud topics.*--topic: /a \(2 messages\), /b \(1 message\)"):
        BagScans(topics_bag)
    with pytest.raises(BagError, match="topic /c is not in the bag; point cloud topics: /a"):
        BagScans(topics_bag, "/c")
    with pytest.raises(BagError, match="topic /s is a std_msgs/msg/String topic"):
        BagScans(topics_bag, "/s")


def test_bad_bags(tmp_path, topics_bag, frames):
    write_bag(tmp_path / "good.bag", "ros1", frames)
    data = (tmp_path / "good.bag").read_bytes()
    (tmp_path / "truncated.bag").write_bytes(data[: len(data) // 2])
    (tmp_path / "random.bag").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp_path / "random.mcap").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp_path / "notes.txt").write_text("hello")
    with Writer1(tmp_path / "strings.bag") as writer:
        s = writer.add_connection("/s", "std_msgs/msg/String", typestore=ROS1)
        writer.write(s, 1, ROS1.serialize_ros1(ROS1.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    cases = {
        "missing.bag": "no such file",
        "truncated.bag": "corrupt or truncated",
        "random.bag": "not a ROS1 bag",
        "random.mcap": "not an MCAP file",
        "notes.txt": "not a bag",
        "strings.bag": r"no sensor_msgs/PointCloud2 or Livox CustomMsg topic \(topics: /s \(std_msgs/msg/String\)\)",
    }
    for name, message in cases.items():
        with pytest.raises(BagError, match=message) as error:
            BagScans(tmp_path / name)
        assert str(tmp_path / name) in str(error.value) and "\n" not in str(error.value)
