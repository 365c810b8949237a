"""ROS bags of LiDAR scans: `reader` (BagScans), the message codecs `pointcloud2` (sensor_msgs/PointCloud2) and
`livox` (Livox CustomMsg), `writer`."""

from pipelines.io.bags.reader import BagError, BagScans, pointcloud_topics
from pipelines.io.bags.writer import FORMATS, MESSAGES, bag_path, delete_bag, write_bag

__all__ = ["FORMATS", "MESSAGES", "BagError", "BagScans", "bag_path", "delete_bag", "pointcloud_topics", "write_bag"]
