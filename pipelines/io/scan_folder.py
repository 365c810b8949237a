"""Scans stored as files, one per scan: a folder of `.bin` (KITTI: float32 x y z [intensity]), `.pcd` or `.ply` files
sorted by name, and the KITTI odometry layout (a sequence folder with `velodyne/*.bin`, `times.txt` and, for the
ground truth, `poses.txt` and `calib.txt`).

A scan's time: from `times.txt` beside the scans (one line per scan, seconds), else from the file names when they
are time stamps (seconds, or integer milli-, micro- or nanoseconds since the epoch), else `rate` [Hz] (scan i at
i / rate). Per-point times: a PCD/PLY field named as in `lidar_points.TIME_FIELDS`, read by its rules; `.bin`
files have none (their scans are not deskewed).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import open3d as o3d

from pipelines.io.lidar_points import carries_livox_tags, relative_seconds, returns, time_field
from pipelines.io.pointclouds import load_kitti_bin
from pipelines.io.trajectory import read_kitti
from sandro_slam.scan import Scan

SCAN_SUFFIXES = (".bin", ".pcd", ".ply")
TIMES_FILE = "times.txt"
EPOCH_AFTER = 1e8  # [s] stamps read from file names must lie after 1973: smaller numbers are indices


class ScanFolder:
    """The scans of a folder, streamed one file at a time in name order (`len`, iteration yields `Scan`s).

    `ScanFolder(path, rate=None)` lists the files and the scan times and raises ValueError (one line naming the
    folder) when there are no scan files, files of more than one format, or no times or not one time per scan. A file
    that cannot be read raises ValueError when its turn comes. `kitti` says whether it is a KITTI sequence folder.
    """

    def __init__(self, path: str | Path, rate: float | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise ValueError(f"{self.path}: no such folder")
        self.kitti = (self.path / "velodyne").is_dir()
        self.scan_dir = self.path / "velodyne" if self.kitti else self.path
        self.files = _scan_files(self.scan_dir)
        self.format = "kitti" if self.kitti else self.files[0].suffix[1:]
        self.stamps = _scan_times(self.files, self.path, rate)

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Scan]:
        for path, stamp in zip(self.files, self.stamps):
            points, times = _read_scan(path, float(stamp))
            yield Scan(float(stamp), points, times)

    def __enter__(self) -> ScanFolder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Nothing stays open between scans; here for the same use as a bag."""

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A KITTI sequence's `poses.txt` as (times, T_world_velodyne per scan): the camera poses moved into the
        LiDAR frame with `calib.txt`'s `Tr` (velodyne -> camera 0); None without poses.txt."""
        poses_file = self.path / "poses.txt"
        if not (self.kitti and poses_file.is_file()):
            return None
        poses = read_kitti(poses_file)
        if len(poses) != len(self.files):
            raise ValueError(f"{poses_file}: {len(poses)} poses for {len(self.files)} scans")
        T_cam_velo = _kitti_calibration(self.path / "calib.txt")
        return self.stamps, np.linalg.inv(T_cam_velo) @ poses @ T_cam_velo


def _scan_files(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)
    if not files:
        raise ValueError(f"{folder}: no scan files ({', '.join(SCAN_SUFFIXES)})")
    suffixes = sorted({p.suffix.lower() for p in files})
    if len(suffixes) > 1:
        raise ValueError(f"{folder}: scans of several formats ({', '.join(suffixes)}): one format per folder")
    return files


def _scan_times(files: list[Path], folder: Path, rate: float | None) -> np.ndarray:
    """(N,) scan times [s]: times.txt, else the file names, else `rate`."""
    times_file = folder / TIMES_FILE
    if times_file.is_file():
        try:
            times = np.loadtxt(times_file, ndmin=1, dtype=np.float64)
        except ValueError as error:
            raise ValueError(f"{times_file}: not one time per line ({error})") from None
        if times.ndim != 1 or len(times) != len(files):
            raise ValueError(f"{times_file}: {times.size} times for {len(files)} scans")
        return times
    stamps = stamps_from_names([p.stem for p in files])
    if stamps is not None:
        return stamps
    if rate is not None:
        return np.arange(len(files)) / rate
    raise ValueError(
        f"{folder}: no scan times: put a {TIMES_FILE} beside the scans, name them by time stamp or give the rate"
    )


def stamps_from_names(stems: list[str]) -> np.ndarray | None:
    """Scan times [s] when every file name is a time stamp since the epoch and they increase: seconds
    (`1700000000.123`), or integer milli-, micro- or nanoseconds (`1700000000123456789`); None otherwise."""
    try:
        values = [int(stem) if stem.isdigit() else float(stem) for stem in stems]
    except ValueError:
        return None
    largest = max(values)
    scale = 1e-9 if largest >= 1e17 else 1e-6 if largest >= 1e14 else 1e-3 if largest >= 1e11 else 1.0
    seconds = np.array([value * scale for value in values], dtype=np.float64)
    if seconds.min() < EPOCH_AFTER or np.any(np.diff(seconds) <= 0.0):
        return None
    return seconds


def _read_scan(path: Path, stamp: float) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float64 [m], per-point times [s] relative to `stamp` or empty) of one scan file; the points
    that are no returns, or that a Livox sensor tagged as noise, dropped (`lidar_points.returns`)."""
    if path.suffix.lower() == ".bin":
        try:
            return load_kitti_bin(path), np.empty(0)
        except OSError as error:
            raise ValueError(f"{path}: cannot read it ({error.strerror})") from None
    cloud = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise ValueError(f"{path}: no points read (not a readable point cloud file)")
    points = cloud.point.positions.numpy().astype(np.float64)
    name = time_field(cloud.point)
    times = relative_seconds(cloud.point[name].numpy(), stamp) if name else np.empty(0)
    livox = carries_livox_tags(cloud.point, "tag" in cloud.point and cloud.point["tag"].dtype == o3d.core.uint8)
    keep = returns(points, cloud.point["tag"].numpy().reshape(-1) if livox else None)
    if keep is not None:
        points = points[keep]
        times = times[keep] if len(times) else times
    return points, times


def _kitti_calibration(path: Path) -> np.ndarray:
    """T_camera0_velodyne (4x4) from a KITTI calib.txt's `Tr:` line; the identity without the file."""
    T = np.eye(4)
    if not path.is_file():
        return T
    for line in path.read_text().splitlines():
        if line.startswith("Tr:"):
            T[:3, :] = np.array(line.split()[1:], dtype=np.float64).reshape(3, 4)
            return T
    raise ValueError(f"{path}: no 'Tr:' line (the velodyne -> camera transform)")
