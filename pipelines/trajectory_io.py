"""Trajectory files: TUM (`t x y z qx qy qz qw`) and KITTI (the 3x4 matrix row by row)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def write_tum(path: Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write (N,) timestamps [s] and (N, 4, 4) poses T_world_sensor as a TUM trajectory."""
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    rows = np.column_stack([timestamps, poses[:, :3, 3], quaternions])
    np.savetxt(path, rows, fmt="%.9f")


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4)) from a TUM file; ValueError if it is not one."""
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as error:
        raise ValueError(f"{path}: not a TUM trajectory ({error})") from None
    if rows.shape[1] != 8 or len(rows) == 0:
        raise ValueError(f"{path}: a TUM trajectory has 8 columns (t x y z qx qy qz qw), found {rows.shape[1]}")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses


def write_kitti(path: Path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) poses as KITTI lines: the top 3x4 of each matrix, row-major."""
    np.savetxt(path, poses[:, :3, :].reshape(len(poses), 12), fmt="%.9f")
