"""What `sandro-slam` reads: a ROS bag, a folder of scans, a KITTI odometry sequence, or a keyframe dump (a folder of
deskewed scans with the poses of the front end that made them), told apart by their layout or named."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipelines.io.bags import POSE_TYPES, BagScans, is_topic_name, read_tf_poses
from pipelines.io.bags.poses import NotAPoseTopic, read_pose_messages
from pipelines.io.bags.tf import TransformTree, frame_name
from pipelines.io.scan_folder import ScanFolder
from pipelines.io.trajectory import read_trajectory

FORMATS = ("bag", "folder", "kitti", "keyframes")
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
DUMP_POSES = ("poses.txt", "poses.tum", "poses.kitti")  # the front end's poses beside a keyframe dump's scans
TF_PREFIX = "tf:"  # `read_poses`: tf:FRAME, the scans' frame in FRAME from a bag's transforms

Poses = tuple[np.ndarray | None, np.ndarray]  # (times [s] or None: one pose per scan in order, (N, 4, 4) poses)


@dataclass
class ScanInput:
    """An opened input: `scans` (len, iteration of `Scan`s, close), what metrics.json says of it, and what came with
    it: the ground truth (a KITTI sequence's poses.txt) and the odometry (a keyframe dump's poses)."""

    scans: BagScans | ScanFolder
    description: dict
    ground_truth: Poses | None = None
    odometry: Poses | None = None
    notes: list[str] = field(default_factory=list)  # what was found beside the scans, for the user
    pose_topics: dict[str, str] = field(default_factory=dict)  # a bag's topics of poses: {topic: message type}

    def __enter__(self) -> ScanInput:
        return self

    def __exit__(self, *exc_info) -> None:
        self.scans.close()


def detect_format(path: Path) -> str:
    """The input format of `path`: a bag file or ROS2 bag folder; a folder with velodyne/ (KITTI); a folder of
    scans with one of `DUMP_POSES` beside them (keyframes); any other folder of scans.

    Raises:
        ValueError: no such path.
    """
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    if path.is_file() or path.name == "metadata.yaml" or (path / "metadata.yaml").exists():
        return "bag"
    if (path / "velodyne").is_dir():
        return "kitti"
    if any((path / name).is_file() for name in DUMP_POSES):
        return "keyframes"
    if any(p.suffix in BAG_SUFFIXES[1:] for p in path.iterdir()):
        return "bag"  # a ROS2 bag folder that lost its metadata.yaml
    return "folder"


def open_input(path: str | Path, fmt: str | None = None, topic: str | None = None,
               rate: float | None = None) -> ScanInput:  # fmt: skip
    """Open `path` as `fmt` (None: `detect_format`). `topic` is for bags, `rate` [Hz] for scan folders without
    other times.

    Raises:
        ValueError (BagError for bags): an input that cannot be read as asked, in one line.
    """
    path = Path(path)
    fmt = fmt or detect_format(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown input format {fmt!r}; choose from {', '.join(FORMATS)}")
    if fmt == "bag":
        scans = BagScans(path, topic)
        description = {"input": str(path), "format": "bag", "topic": scans.topic, "messages": len(scans)}
        poses = {name: kind for name, kind in scans.topic_types.items() if kind in POSE_TYPES}
        result = ScanInput(scans, {**description, "stamps": scans.stamps}, pose_topics=poses)
        if scans.stamps == "record":
            result.notes.append(f"{scans.topic}: header.stamp does not change, the scans are timed when recorded")
        return result
    if topic is not None:
        raise ValueError(f"{path}: --topic is for bags, this is a {fmt} input")
    scans = ScanFolder(path, rate)
    if fmt == "kitti" and not scans.kitti:
        raise ValueError(f"{path}: not a KITTI sequence folder (no velodyne/)")
    description = {"input": str(path), "format": fmt, "scans": len(scans)}
    result = ScanInput(scans, description)
    if fmt == "kitti":
        result.ground_truth = scans.ground_truth()
        if result.ground_truth is not None:
            result.notes.append(f"ground truth: {path / 'poses.txt'} (in the LiDAR frame, with calib.txt)")
    if fmt == "keyframes":
        poses_file = next((path / name for name in DUMP_POSES if (path / name).is_file()), None)
        if poses_file is None:
            raise ValueError(f"{path}: a keyframe dump needs its poses beside the scans ({', '.join(DUMP_POSES)})")
        result.odometry = read_trajectory(poses_file)
        result.notes.append(f"odometry: {poses_file} (a keyframe dump; --format folder to run KISS-ICP instead)")
    return result


def names_bag_poses(value: str) -> bool:
    """Whether `value` can name poses inside a bag for `read_poses`: a topic name, or tf:FRAME."""
    return is_topic_name(value) or (value.startswith(TF_PREFIX) and is_topic_name(value[len(TF_PREFIX) :]))


def read_poses(
    value: str, path: str | Path, fmt: str | None = None, topic: str | None = None, notes: list[str] | None = None
) -> Poses:
    """The poses that `value` names for the input at `path` (format `fmt`, None: `detect_format`; `topic` its point
    cloud topic, if a bag has several): a trajectory file (`read_trajectory`) or, for a bag, one of its topics of
    poses (`read_pose_topic`: a front end's nav_msgs/Odometry, a ground truth's geometry_msgs poses), or `tf:FRAME`:
    the pose of the scans' frame (their header.frame_id) in FRAME from the bag's transforms (`read_tf_poses`).

    A topic whose messages name their frame (nav_msgs/Odometry's child_frame_id: base_link, say) other than the
    scans' (lidar) is moved to the scans' frame by the bag's constant transforms between the two (/tf_static), or
    taken as the scans' frame where there are none; what was done goes into `notes`, for the user.

    Raises:
        ValueError (BagError for bags): `value` is none of them, or cannot be read.
    """
    path = Path(path)
    is_bag = not Path(value).is_file() and (fmt or detect_format(path)) == "bag"
    if is_bag and value.startswith(TF_PREFIX):
        with BagScans(path, topic) as scans:
            return read_tf_poses(path, value[len(TF_PREFIX) :], scans.frame_id())
    if not is_bag or not is_topic_name(value):
        return read_trajectory(Path(value))
    try:
        times, poses, child = read_pose_messages(path, value)
    except NotAPoseTopic as error:
        raise ValueError(f"{value}: neither a trajectory file nor a topic of poses in {path} (its topics of poses: "
                         f"{error.listing})") from None  # fmt: skip
    if child is None:  # poses of the frame their messages' headers name: nothing to compare with the scans'
        return times, poses
    with BagScans(path, topic) as scans:
        scans_frame = frame_name(scans.frame_id())
    if not scans_frame or frame_name(child) == scans_frame:
        return times, poses
    extrinsic = TransformTree(path).static(child, scans_frame)
    if notes is not None and extrinsic is not None:
        notes.append(f"{value}: poses of {frame_name(child)} moved into the scans' frame {scans_frame} by the bag's "
                     "constant transforms")  # fmt: skip
    elif notes is not None:
        notes.append(f"{value}: poses of {frame_name(child)}, scans in {scans_frame}, and no constant transform "
                     "between them in the bag: taken as one frame")  # fmt: skip
    return times, poses if extrinsic is None else poses @ extrinsic
