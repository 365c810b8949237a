"""Poses recorded in bags: a front end's nav_msgs/Odometry and geometry_msgs poses read as a trajectory, a topic
told from a file, scans in the odometry's world frame noticed."""

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from pipelines.io.bags import BagError, is_topic_name, pose_topics, read_pose_topic, write_bag
from pipelines.io.bags.pointcloud2 import ros_header
from pipelines.io.inputs import read_poses
from pipelines.io.trajectory import write_tum
from pipelines.scan_frame import ScanFrameCheck, scan_centre
from sandro_core.geometry import transform_points
from sandro_slam import Scan

START = 1_700_000_000.0


def _poses(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=20.0, size=(count, 3))
    return poses


def _scans(times: np.ndarray, seed: int = 0) -> list[Scan]:
    rng = np.random.default_rng(seed)
    return [Scan(t, rng.normal(scale=5.0, size=(200, 3)), np.empty(0)) for t in times]


@pytest.mark.parametrize(("fmt", "name"), [("ros1", "a.bag"), ("ros2-sqlite3", "b"), ("ros2-mcap", "c")])
def test_odometry_written_beside_the_scans_reads_back(tmp_path, fmt, name):
    times = START + 0.1 * np.arange(12)
    poses = _poses(12)
    path = tmp_path / name
    assert write_bag(path, fmt, _scans(times), odometry=zip(times, poses), odometry_topic="/lio/odometry") == 12
    assert pose_topics(path) == {"/lio/odometry": "nav_msgs/msg/Odometry"}
    read_times, read = read_pose_topic(path, "/lio/odometry")
    np.testing.assert_allclose(read_times, times, rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(read, poses, rtol=0.0, atol=1e-9)
    with pytest.raises(BagError, match=r"/points is not a topic of poses .*/lio/odometry \(nav_msgs/Odometry\)"):
        read_pose_topic(path, "/points")


def test_odometry_whose_time_goes_back_leaves_no_bag(tmp_path):
    times = START + 0.1 * np.arange(5)
    odometry = zip(times[[0, 1, 3, 2, 4]], _poses(5))
    with pytest.raises(ValueError, match="must not go back"):
        write_bag(tmp_path / "a.bag", "ros1", _scans(times), odometry=odometry)
    assert not any(tmp_path.iterdir())


def _write_messages(path, msgtype: str, messages: list[tuple[int, object]], topic: str = "/pose") -> None:
    """A ROS2 sqlite3 bag of (record time [ns], message) on one topic."""
    typestore = get_typestore(Stores.LATEST)
    with Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=typestore)
        for record, msg in messages:
            writer.write(connection, record, typestore.serialize_cdr(msg, msgtype))


def _geometry_message(msgtype: str, stamp: float, pose: np.ndarray):
    types = get_typestore(Stores.LATEST).types
    x, y, z = pose[:3, 3]
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    header = ros_header(get_typestore(Stores.LATEST), stamp, "map")
    if msgtype == "geometry_msgs/msg/TransformStamped":
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )
        return types[msgtype](header=header, child_frame_id="lidar", transform=transform)
    geometry = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return types[msgtype](header=header, pose=geometry)
    covariance = types["geometry_msgs/msg/PoseWithCovariance"](pose=geometry, covariance=np.zeros(36))
    return types[msgtype](header=header, pose=covariance)


@pytest.mark.parametrize(
    "msgtype",
    [
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/msg/TransformStamped",
    ],
)
def test_geometry_poses_sorted_by_stamp_the_last_of_a_stamp_kept(tmp_path, msgtype):
    poses = _poses(5, seed=1)
    stamps = [START + 0.2, START, START + 0.1, START + 0.1, START + 0.3]  # out of order; one stamp twice
    messages = [
        (round((START + k) * 1e9), _geometry_message(msgtype, stamp, pose))
        for k, (stamp, pose) in enumerate(zip(stamps, poses))
    ]
    _write_messages(tmp_path / "bag", msgtype, messages)
    times, read = read_pose_topic(tmp_path / "bag", "/pose")
    np.testing.assert_allclose(times - START, [0.0, 0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(read, poses[[1, 3, 0, 4]], atol=1e-9)  # of the two at 0.1, the one recorded later


def test_poses_whose_stamps_never_change_are_timed_when_recorded(tmp_path):
    poses = _poses(3, seed=2)
    messages = [(round((START + k) * 1e9), _geometry_message("geometry_msgs/msg/PoseStamped", 0.0, p))
                for k, p in enumerate(poses)]  # fmt: skip
    _write_messages(tmp_path / "bag", "geometry_msgs/msg/PoseStamped", messages)
    times, _ = read_pose_topic(tmp_path / "bag", "/pose")
    np.testing.assert_allclose(times - START, [0.0, 1.0, 2.0], atol=1e-6)


def test_a_pose_that_is_not_one_is_named(tmp_path):
    pose = _poses(1)[0]
    msg = _geometry_message("geometry_msgs/msg/PoseStamped", START, pose)
    msg.pose.orientation.w = msg.pose.orientation.x = msg.pose.orientation.y = msg.pose.orientation.z = 0.0
    good = _geometry_message("geometry_msgs/msg/PoseStamped", START - 1.0, pose)
    _write_messages(tmp_path / "bag", "geometry_msgs/msg/PoseStamped", [(1, good), (2, msg)])
    with pytest.raises(BagError, match="/pose message 1: not a valid pose .*length 0"):
        read_pose_topic(tmp_path / "bag", "/pose")


def test_an_option_names_a_trajectory_file_or_a_topic_of_the_bag(tmp_path):
    times = START + 0.1 * np.arange(4)
    poses = _poses(4)
    bag = tmp_path / "drive.bag"
    write_bag(bag, "ros1", _scans(times), odometry=zip(times, poses))
    np.testing.assert_allclose(read_poses("/odometry", bag)[1], poses, atol=1e-9)
    write_tum(tmp_path / "poses.tum", times, poses[::-1])
    np.testing.assert_allclose(read_poses(str(tmp_path / "poses.tum"), bag)[1], poses[::-1], atol=1e-9)
    with pytest.raises(ValueError, match=r"/odom: neither a trajectory file nor a topic of poses .*/odometry \(nav_"):
        read_poses("/odom", bag)
    with pytest.raises(ValueError, match="no such trajectory file"):
        read_poses("missing.tum", bag)  # a file name, not a topic
    assert is_topic_name("/Odometry") and is_topic_name("lio_sam/mapping/odometry") and is_topic_name("~/odom")
    assert not is_topic_name("poses.tum") and not is_topic_name("/data/gt.txt") and not is_topic_name("")


def test_scans_in_a_world_frame_are_noticed():
    # A drive around a 40 m circle; each scan a cloud around the sensor, given in the sensor frame or moved into
    # the world frame by its pose (what picking FAST-LIO2's /cloud_registered gives).
    count = 80
    angles = np.linspace(0.0, 1.5 * np.pi, count)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", (angles + np.pi / 2)[:, None]).as_matrix()
    poses[:, :2, 3] = 40.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    checks = {name: ScanFrameCheck() for name in ("sensor", "world", "standing")}
    verdicts = []
    for pose, scan in zip(poses, _scans(START + 0.1 * np.arange(count))):
        points = scan.points + [20.0, 0.0, 0.0]  # looking ahead, as a Livox does
        world = transform_points(pose, points)
        checks["sensor"].add(scan_centre(points), pose)
        checks["world"].add(scan_centre(world), pose)  # a given odometry on world-frame scans
        checks["standing"].add(scan_centre(world), np.eye(4))  # KISS-ICP on them: they line up where they are
        verdicts.append({name: (check.world_frame, check.fixed_frame) for name, check in checks.items()})
    assert verdicts[-1] == {"sensor": (False, False), "world": (True, False), "standing": (False, True)}
    assert verdicts[ScanFrameCheck.MIN_SCANS - 2] == {name: (False, False) for name in checks}  # too few scans yet
    assert not any(v["sensor"][0] or v["sensor"][1] for v in verdicts)
