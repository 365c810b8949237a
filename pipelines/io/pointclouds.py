"""Point cloud files: PLY/PCD (Open3D) and KITTI Velodyne .bin, read and written; clouds built from submaps."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import open3d as o3d

from pipelines.io.atomic import atomic_path
from sandro_core.geometry import transform_points


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


def write_point_cloud(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    dtype: type = np.float64,
    fields: dict[str, np.ndarray] | None = None,
) -> int:
    """Write (N, 3) points as a binary PLY or PCD (by the suffix of `path`), atomically: coordinates as `dtype`
    (float64: "double", float32: "float"), colors (N, 3) in [0, 1] as 8-bit RGB when given, and `fields`: extra
    per-point values (N,) by name, of their own type (e.g. a per-point time `t`). Returns the number of points."""
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points, dtype=dtype)))
    if colors is not None:
        cloud.point.colors = o3d.core.Tensor(np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8))
    for name, values in (fields or {}).items():
        cloud.point[name] = o3d.core.Tensor(np.ascontiguousarray(values).reshape(-1, 1))
    with atomic_path(path) as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), cloud):
            raise OSError(f"could not write {path}")
    return len(points)


def write_kitti_bin(path: str | Path, points: np.ndarray) -> None:
    """Write (N, 3) points as a KITTI Velodyne .bin (float32 x y z intensity, intensity 0), atomically."""
    records = np.zeros((len(points), 4), dtype=np.float32)
    records[:, :3] = points
    with atomic_path(path) as tmp:
        records.tofile(tmp)


def submaps_cloud(submaps: Iterable[tuple[np.ndarray, np.ndarray]], voxel: float) -> np.ndarray:
    """(M, 3) points of submaps given as (points in the keyframe frame, T_world_keyframe), moved into the world
    frame, one point per `voxel` [m] (voxelised every 20 submaps on the way: memory stays bounded on long runs)."""
    cloud = o3d.geometry.PointCloud()
    for index, (points, T) in enumerate(submaps):
        cloud.points.extend(o3d.utility.Vector3dVector(transform_points(T, points)))
        if index % 20 == 19:
            cloud = cloud.voxel_down_sample(voxel)
    return np.asarray(cloud.voxel_down_sample(voxel).points)
