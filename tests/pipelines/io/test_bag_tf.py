"""Poses along a bag's transform tree: a robot's odometry (odom -> base_link on /tf) composed with the LiDAR's
extrinsic (base_link -> lidar on /tf_static) into the pose of the scans' frame."""

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from pipelines.io.bags import BagError, read_tf_poses
from pipelines.io.bags.pointcloud2 import POINTCLOUD2, encode_pointcloud2, ros_header, scan_cloud
from pipelines.io.inputs import names_bag_poses, read_poses

START = 1_700_000_000.0
TF = "tf2_msgs/msg/TFMessage"


def _pose(yaw: float, xyz) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    pose[:3, 3] = xyz
    return pose


def _transform(store, stamp: float, parent: str, child: str, pose: np.ndarray):
    types = store.types
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return types["geometry_msgs/msg/TransformStamped"](
        header=ros_header(store, stamp, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )


def _odometry(store, stamp: float, child: str, pose: np.ndarray):
    types = store.types
    transform = _transform(store, stamp, "odom", child, pose).transform
    geometry = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
        orientation=transform.rotation,
    )
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return types["nav_msgs/msg/Odometry"](
        header=ros_header(store, stamp, "odom"),
        child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=geometry, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
        ),
    )


ODOM_TIMES = START + 0.02 * np.arange(50)  # 50 Hz odometry over a second
T_BASE_LIDAR = _pose(0.3, [0.4, -0.1, 1.2])


def _odom_base(times: np.ndarray) -> np.ndarray:
    return np.stack([_pose(0.5 * (t - START), [2.0 * (t - START), 0.1 * (t - START), 0.0]) for t in times])


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A ROS2 bag: /tf (map -> odom static-like, odom -> base_link moving), /tf_static (base_link -> lidar,
    base_link -> imu), and /points in frame lidar."""
    path = tmp_path_factory.mktemp("tf") / "robot"
    store = get_typestore(Stores.LATEST)
    with Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=StoragePlugin.SQLITE3) as writer:
        tf = writer.add_connection("/tf", TF, typestore=store)
        tf_static = writer.add_connection("/tf_static", TF, typestore=store)
        points = writer.add_connection("/points", POINTCLOUD2, typestore=store)
        statics = [_transform(store, START, "base_link", "lidar", T_BASE_LIDAR),
                   _transform(store, START, "base_link", "imu", _pose(0.0, [0.0, 0.0, 0.5]))]  # fmt: skip
        writer.write(tf_static, round(START * 1e9), store.serialize_cdr(store.types[TF](transforms=statics), TF))
        for name, child in (("/odom", "base_link"), ("/wheel_odom", "wheel")):  # nav_msgs/Odometry of base_link
            connection = writer.add_connection(name, "nav_msgs/msg/Odometry", typestore=store)
            for t, pose in zip(ODOM_TIMES, _odom_base(ODOM_TIMES)):
                writer.write(connection, round(t * 1e9), store.serialize_cdr(_odometry(store, t, child, pose),
                                                                             "nav_msgs/msg/Odometry"))  # fmt: skip
        for t, pose in zip(ODOM_TIMES, _odom_base(ODOM_TIMES)):
            transforms = [_transform(store, t, "/odom", "base_link", pose),  # a ROS1-style leading slash
                          _transform(store, t, "map", "odom", _pose(0.0, [5.0, 0.0, 0.0]))]  # fmt: skip
            writer.write(tf, round(t * 1e9), store.serialize_cdr(store.types[TF](transforms=transforms), TF))
        for k in range(5):
            stamp = START + 0.2 * k
            cloud = encode_pointcloud2(store, stamp, scan_cloud(np.random.default_rng(k).normal(size=(100, 3)),
                                                                np.empty(0)), "lidar")  # fmt: skip
            writer.write(points, round(stamp * 1e9), store.serialize_cdr(cloud, POINTCLOUD2))
    return path


def test_the_scans_frame_in_the_odometry_frame_along_the_tree(bag):
    times, poses = read_tf_poses(bag, "odom", "lidar")
    np.testing.assert_allclose(times, ODOM_TIMES, atol=1e-6)
    np.testing.assert_allclose(poses, _odom_base(ODOM_TIMES) @ T_BASE_LIDAR, atol=1e-9)
    _, inverse = read_tf_poses(bag, "lidar", "map")  # against the transforms' direction, through a static one
    expected = np.linalg.inv(_pose(0.0, [5.0, 0.0, 0.0]) @ _odom_base(ODOM_TIMES) @ T_BASE_LIDAR)
    np.testing.assert_allclose(inverse, expected, atol=1e-9)
    times, poses = read_poses("tf:odom", bag)  # the frame of /points' scans: lidar
    np.testing.assert_allclose(poses, _odom_base(ODOM_TIMES) @ T_BASE_LIDAR, atol=1e-9)


def test_frames_without_a_moving_chain_are_refused_with_the_frames_named(bag):
    with pytest.raises(BagError, match="no chain of transforms from odom to camera .*frames: base_link, imu, lidar"):
        read_tf_poses(bag, "odom", "camera")
    with pytest.raises(BagError, match="every transform from imu to lidar is static"):
        read_tf_poses(bag, "imu", "lidar")
    assert names_bag_poses("tf:odom") and names_bag_poses("/Odometry") and not names_bag_poses("tf:")


def test_an_odometry_of_another_frame_is_moved_into_the_scans_frame(bag):
    notes = []
    _, poses = read_poses("/odom", bag, notes=notes)  # poses of base_link, scans in lidar
    np.testing.assert_allclose(poses, _odom_base(ODOM_TIMES) @ T_BASE_LIDAR, atol=1e-9)
    assert notes == ["/odom: poses of base_link moved into the scans' frame lidar by the bag's constant transforms"]
    notes.clear()
    _, poses = read_poses("/wheel_odom", bag, notes=notes)  # a frame the tree does not have: taken as the scans'
    np.testing.assert_allclose(poses, _odom_base(ODOM_TIMES), atol=1e-9)
    assert "poses of wheel, scans in lidar, and no constant transform between them" in notes[0]
