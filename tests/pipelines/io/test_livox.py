"""Livox CustomMsg: decoding the serialized bytes (checked against rosbags' own deserialisation), bags of it."""

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from pipelines.io.bags import FORMATS, BagError, BagScans, pointcloud_topics, write_bag
from pipelines.io.bags.livox import (
    CUSTOM_MSG_TYPES,
    CustomMsgError,
    custom_msg_arrays,
    custom_msg_frame_id,
    encode_custom_msg,
    register_custom_msg,
)
from pipelines.io.bags.pointcloud2 import encode_pointcloud2, pointcloud2_arrays
from pipelines.simulation import simulate_sequence

STAMP = 1_700_000_123.25  # [s], exactly representable in ns


def typestore(ros1: bool, msgtype: str):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    register_custom_msg(store, msgtype)
    return store


def serialized(ros1: bool, msgtype: str, msg, little_endian: bool = True) -> bytes:
    store = typestore(ros1, msgtype)
    if ros1:
        return store.serialize_ros1(msg, msgtype)
    return store.serialize_cdr(msg, msgtype, little_endian=little_endian)


def points_and_times(n: int = 500, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-40.0, 40.0, (n, 3)).astype(np.float32).astype(np.float64)
    return points, np.sort(rng.uniform(0.0, 0.1, n))


@pytest.mark.parametrize("msgtype", CUSTOM_MSG_TYPES)
@pytest.mark.parametrize(("ros1", "little_endian"), [(True, True), (False, True), (False, False)])
def test_decoding_matches_rosbags_for_every_frame_id_alignment(msgtype, ros1, little_endian):
    points, times = points_and_times()
    points[7] = 0.0  # no return: dropped with its time
    store = typestore(ros1, msgtype)
    for frame_id in ("", "a", "ab", "abc", "livox", "livox_frame", "lidar_link"):  # every alignment of what follows
        msg = encode_custom_msg(store, msgtype, STAMP, points, times, frame_id)
        msg.timebase += 2_000_000  # a timebase after the stamp shifts every time
        raw = serialized(ros1, msgtype, msg, little_endian)
        stamp_ns, decoded, decoded_times = custom_msg_arrays(raw, cdr=not ros1)
        assert custom_msg_frame_id(raw, cdr=not ros1) == frame_id

        reference = store.deserialize_ros1(raw, msgtype) if ros1 else store.deserialize_cdr(raw, msgtype)
        expected = np.array([(p.x, p.y, p.z) for p in reference.points], dtype=np.float32).astype(np.float64)
        offsets = np.array([p.offset_time for p in reference.points])
        keep = np.any(expected != 0.0, axis=1)
        assert stamp_ns == reference.header.stamp.sec * 10**9 + reference.header.stamp.nanosec == round(STAMP * 1e9)
        np.testing.assert_array_equal(decoded, expected[keep])
        np.testing.assert_allclose(decoded_times, offsets[keep] * 1e-9 + 0.002, atol=1e-12)
        np.testing.assert_allclose(decoded_times, times[keep] + 0.002, atol=1e-9)


def test_empty_message_constant_times_and_truncation():
    msgtype = CUSTOM_MSG_TYPES[0]
    store = typestore(True, msgtype)
    stamp_ns, points, times = custom_msg_arrays(serialized(True, msgtype, encode_custom_msg(store, msgtype, STAMP,
                                                np.empty((0, 3)), np.empty(0))), cdr=False)  # fmt: skip
    assert stamp_ns == round(STAMP * 1e9) and points.shape == (0, 3) and times.shape == (0,)
    p, _ = points_and_times()
    raw = serialized(True, msgtype, encode_custom_msg(store, msgtype, STAMP, p, np.empty(0)))  # offset_time all 0
    _, points, times = custom_msg_arrays(raw, cdr=False)
    assert len(points) == len(p) and times.shape == (0,)  # a driver that fills no time: no deskewing
    with pytest.raises(CustomMsgError, match=r"has \d+ bytes, its 500 points need"):
        custom_msg_arrays(raw[:-1], cdr=False)
    with pytest.raises(CustomMsgError, match="ends inside its header"):
        custom_msg_arrays(raw[:20], cdr=False)
    with pytest.raises(ValueError, match="one per point"):
        encode_custom_msg(store, msgtype, STAMP, p, np.zeros(3))


# Livox tags: bits 0-1 noise by spatial position, 2-3 by intensity, 4-5 return number, 6-7 (Mid-70) waveform
# distortion; 01 in a noise group is high confidence.
TAGS = np.array([0x00, 0x01, 0x02, 0x03, 0x04, 0x08, 0x10, 0x20, 0x40, 0x11, 0x12])
NOISE = np.array([False, True, False, False, True, False, False, False, True, True, False])


@pytest.mark.parametrize("ros1", [True, False])
def test_points_tagged_as_noise_are_dropped_from_custom_msgs(ros1):
    msgtype = CUSTOM_MSG_TYPES[1]
    points, times = points_and_times(len(TAGS))
    msg = encode_custom_msg(typestore(ros1, msgtype), msgtype, STAMP, points, times, tags=TAGS)
    _, decoded, decoded_times = custom_msg_arrays(serialized(ros1, msgtype, msg), cdr=not ros1)
    np.testing.assert_array_equal(decoded, points[~NOISE])
    np.testing.assert_allclose(decoded_times, times[~NOISE], atol=1e-9)


def test_points_tagged_as_noise_are_dropped_from_livox_pointclouds():
    # livox_ros_driver2's PointCloud2: x y z intensity (float32), tag line (uint8), timestamp (float64, ns).
    points, times = points_and_times(len(TAGS))
    layout = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("tag", "u1"), ("line", "u1"),
              ("timestamp", "f8")]  # fmt: skip
    cloud = np.zeros(len(TAGS), dtype=layout)
    for k, axis in enumerate("xyz"):
        cloud[axis] = points[:, k]
    cloud["tag"], cloud["timestamp"] = TAGS, (STAMP + times) * 1e9
    msg = encode_pointcloud2(get_typestore(Stores.LATEST), STAMP, cloud)
    decoded, decoded_times = pointcloud2_arrays(msg)
    np.testing.assert_array_equal(decoded, points[~NOISE])
    np.testing.assert_allclose(decoded_times, times[~NOISE], atol=1e-6)
    unnamed = encode_pointcloud2(get_typestore(Stores.LATEST), STAMP, cloud[["x", "y", "z", "tag"]])
    assert len(pointcloud2_arrays(unnamed)[0]) == len(TAGS)  # a tag without Livox's line field: not Livox's


@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_round_trip(tmp_path, fmt):
    sequence = simulate_sequence(seed=1, frames=2)
    frames = [(STAMP + f.timestamp, f.points, f.times) for f in sequence.frames()]
    path = tmp_path / ("scans.bag" if fmt == "ros1" else f"scans_{fmt}")
    assert write_bag(path, fmt, frames, topic="/livox/lidar", message="livox", frame_id="livox_frame") == 2
    assert pointcloud_topics(path) == {"/livox/lidar": 2}
    with BagScans(path) as bag:
        assert bag.duration == pytest.approx(0.1, abs=1e-6) and bag.frame_id() == "livox_frame"
        read = list(bag)
    for (stamp, points, times), (stamp0, points0, times0) in zip(read, frames, strict=True):
        assert stamp == pytest.approx(stamp0, abs=1e-6)
        np.testing.assert_array_equal(points, points0.astype(np.float32))
        np.testing.assert_allclose(times, times0, atol=1e-9)


def test_a_truncated_message_in_a_bag_is_named(tmp_path):
    msgtype = CUSTOM_MSG_TYPES[0]
    p, t = points_and_times(50)
    raw = serialized(True, msgtype, encode_custom_msg(typestore(True, msgtype), msgtype, STAMP, p, t))
    with Writer1(tmp_path / "a.bag") as writer:
        connection = writer.add_connection("/livox/lidar", msgtype, typestore=typestore(True, msgtype))
        writer.write(connection, 1, raw)
        writer.write(connection, 2, raw[:-19])  # one point short
        writer.write(connection, 3, raw)
    with BagScans(tmp_path / "a.bag") as bag, pytest.raises(BagError) as error:
        list(bag)
    assert str(error.value).startswith(f"{tmp_path / 'a.bag'}: /livox/lidar message 1: CustomMsg data has")
