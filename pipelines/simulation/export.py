"""A simulated drive written as a ROS bag (sensor_msgs/PointCloud2 or Livox CustomMsg) or as a folder of scan files,
with its ground truth beside it (what `sandro-simulate` writes).

Folder formats:
    folder      the raw scans as PCD files (x, y, z float32 and t uint32 [ns] after the sweep start: the same points
                and times as the bag's messages), times.txt the sweep starts
    kitti       the KITTI odometry layout: velodyne/<i>.bin deskewed to each sweep's end (float32 x y z, intensity
                0), times.txt those times, poses.txt the true poses then (KITTI, LiDAR frame: no calib.txt needed)
    keyframes   a keyframe dump of a LiDAR-inertial front end: the deskewed scans as PCD files (x, y, z), times.txt,
                and poses.txt the front end's odometry: the true poses drifting by `drift` of the distance
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from pipelines.io.atomic import atomic_dir, atomic_path
from pipelines.io.bags import write_bag
from pipelines.io.pointclouds import write_kitti_bin, write_point_cloud
from pipelines.io.trajectory import write_kitti, write_tum
from pipelines.simulation.drift import Drift, drifted
from pipelines.simulation.sequence import SimulatedSequence, simulate_sequence
from sandro_slam.scan import Scan

BAG_FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")
FOLDER_FORMATS = ("folder", "kitti", "keyframes")
GROUND_TRUTH_RATE = 100.0  # [Hz]
DEFAULT_START_TIME = 1_700_000_000.0  # [s] header.stamp of the first sweep (2023-11-14, a plausible ROS time)


def ground_truth_path(out: str | Path) -> Path:
    """Where `sandro-simulate OUT` writes the ground truth: OUT.gt.tum beside OUT."""
    out = Path(out)
    return out.with_name(out.name + ".gt.tum")


def simulate(
    out: Path,
    fmt: str,
    seed: int = 0,
    laps: int = 2,
    frames: int | None = None,
    noise: float = 0.02,
    topic: str = "/points",
    start_time: float = DEFAULT_START_TIME,
    drift: float = 0.005,
    overwrite: bool = False,
    progress: bool = False,
    message: str = "pointcloud2",
    odometry_topic: str | None = None,
) -> int:
    """Simulate a drive (`simulate_sequence(seed, laps, frames, noise)`) into `out` as a bag (`BAG_FORMATS`) or a
    scan folder (`FOLDER_FORMATS`), and its ground truth T_world_sensor into `ground_truth_path(out)`, at 100 Hz on
    the clock of the scans (sweep starts from `start_time`); returns the number of scans. Both appear together at
    the end (each written atomically), or neither on an error. `topic` and `message` (`pipelines.io.bags.MESSAGES`)
    are the bag's. With `odometry_topic` a bag holds what a LiDAR-inertial front end (FAST-LIO2, LIO-SAM)
    publishes: each scan deskewed with the true motion to its sweep's end, without per-point times, and on that
    topic its odometry as nav_msgs/Odometry, the true poses drifting by `drift` of the distance (as the keyframe
    dump's)."""
    if fmt not in BAG_FORMATS + FOLDER_FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(BAG_FORMATS + FOLDER_FORMATS)}")
    sequence = simulate_sequence(seed=seed, laps=laps, frames=frames, noise_sigma=noise)
    period = sequence.lidar.sweep_period
    gt_times = np.arange(round(len(sequence) * period * GROUND_TRUTH_RATE) + 1) / GROUND_TRUTH_RATE
    indices = range(len(sequence))
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, unit="scan", desc="sandro-simulate", dynamic_ncols=True)
    with atomic_path(ground_truth_path(out)) as gt_tmp:
        write_tum(gt_tmp, start_time + gt_times, sequence.poses_at(gt_times))
        if fmt in BAG_FORMATS and odometry_topic is not None:
            # Streamed: the writer takes each pose just before its scan, so the two copies stay one scan apart
            for_scans, for_poses = itertools.tee(sequence.deskewed(i) for i in indices)
            odometry = Drift(drift)
            return write_bag(
                out, fmt, (Scan(start_time + scan.timestamp, scan.points, scan.times) for scan, _ in for_scans),
                topic=topic, overwrite=overwrite, message=message, odometry_topic=odometry_topic,
                odometry=((start_time + scan.timestamp, odometry(T)) for scan, T in for_poses),
            )  # fmt: skip
        if fmt in BAG_FORMATS:
            scans = (sequence.frame(i) for i in indices)
            return write_bag(
                out, fmt, (Scan(start_time + f.timestamp, f.points, f.times) for f in scans), topic=topic,
                overwrite=overwrite, message=message,
            )  # fmt: skip
        return _write_folder(out, fmt, sequence, indices, start_time, drift, overwrite)


def _write_folder(
    out: Path, fmt: str, sequence: SimulatedSequence, indices, start_time: float, drift: float, overwrite: bool
) -> int:
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise FileExistsError(f"{out} exists")
    with atomic_dir(out) as folder:
        scans = folder / "velodyne" if fmt == "kitti" else folder
        scans.mkdir(parents=True)
        stamps, poses = [], []
        for index in indices:
            if fmt == "folder":
                frame = sequence.frame(index)
                stamps.append(start_time + frame.timestamp)
                write_point_cloud(scans / f"{index:06d}.pcd", frame.points, dtype=np.float32,
                                  fields={"t": np.round(frame.times * 1e9).astype(np.uint32)})  # fmt: skip
                continue
            scan, T_world_sensor = sequence.deskewed(index)
            stamps.append(start_time + scan.timestamp)
            poses.append(T_world_sensor)
            if fmt == "kitti":
                write_kitti_bin(scans / f"{index:06d}.bin", scan.points)
            else:
                write_point_cloud(scans / f"{index:06d}.pcd", scan.points, dtype=np.float32)
        np.savetxt(folder / "times.txt", np.array(stamps), fmt="%.9f")
        if poses:
            write_kitti(
                folder / "poses.txt", drifted(np.array(poses), drift) if fmt == "keyframes" else np.array(poses)
            )
    return len(stamps)
