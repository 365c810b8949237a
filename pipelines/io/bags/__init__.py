"""ROS bags of sensor_msgs/PointCloud2 scans: `reader` (BagScans), `pointcloud2` (the message codec), `writer`."""

from pipelines.io.bags.reader import BagError, BagScans, pointcloud_topics
from pipelines.io.bags.writer import FORMATS, bag_path, delete_bag, write_bag

__all__ = ["FORMATS", "BagError", "BagScans", "bag_path", "delete_bag", "pointcloud_topics", "write_bag"]
