"""Point cloud file readers: PLY/PCD (via Open3D) and KITTI Velodyne .bin."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d


def load_kitti_bin(path: str | Path, num_fields: int | None = None) -> np.ndarray:
    """Read a KITTI-style .bin of float32 records: x y z, or x y z intensity.

    Args:
        path: the .bin file.
        num_fields: 3 or 4 float32 values per point; None guesses from the file: 4 only when the size
            allows it and every 4th value is a non-negative intensity (x y z files have negative
            coordinates in that column), 3 otherwise.

    Returns:
        (N, 3) float64 points [m] in the sensor frame; intensity is dropped.
    """
    values = np.fromfile(path, dtype=np.float32)
    if num_fields is None:
        as_four = values.size % 4 == 0 and np.all(values.reshape(-1, 4)[:, 3] >= 0.0)
        num_fields = 4 if as_four or values.size % 3 != 0 else 3
    if num_fields not in (3, 4):
        raise ValueError(f"num_fields must be 3 or 4, got {num_fields}")
    if values.size == 0 or values.size % num_fields != 0:
        raise ValueError(f"{path}: {values.size} float32 values do not form records of {num_fields}")
    return values.reshape(-1, num_fields)[:, :3].astype(np.float64)


def load_point_cloud(path: str | Path) -> np.ndarray:
    """Read the points of a .ply, .pcd (Open3D) or KITTI .bin file as (N, 3) float64 [m], file frame.

    Raises:
        ValueError: unknown extension, or a file without points.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such point cloud file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".bin":
        points = load_kitti_bin(path)
    elif suffix in (".ply", ".pcd"):
        points = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    else:
        raise ValueError(f"{path}: unknown point cloud format {suffix!r} (expected .ply, .pcd or .bin)")
    if len(points) == 0:
        raise ValueError(f"{path}: no points read")
    return points
