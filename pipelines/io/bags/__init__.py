"""ROS bags of LiDAR scans: `reader` (BagScans), the message codecs `pointcloud2` (sensor_msgs/PointCloud2) and
`livox` (Livox CustomMsg), `poses` (odometry and ground truth recorded as pose messages), `tf` (poses along the
transform tree), `writer`."""

from pipelines.io.bags.poses import POSE_TYPES, is_topic_name, pose_topics, read_pose_topic
from pipelines.io.bags.reader import BagError, BagScans, pointcloud_topics
from pipelines.io.bags.tf import read_tf_poses
from pipelines.io.bags.writer import FORMATS, MESSAGES, bag_path, delete_bag, write_bag

__all__ = [
    "FORMATS", "MESSAGES", "POSE_TYPES", "BagError", "BagScans", "bag_path", "delete_bag", "is_topic_name",
    "pointcloud_topics", "pose_topics", "read_pose_topic", "read_tf_poses", "write_bag",
]  # fmt: skip
