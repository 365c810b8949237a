"""Pose files: TUM (`t x y z qx qy qz qw`), KITTI (the top 3x4 of each matrix, row by row), a single 4x4
transform, and keyframe pose lists (`vN x y z qx qy qz qw`). Poses are (N, 4, 4) T_world_sensor [m]."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pipelines.io.atomic import atomic_path


def write_tum(path: Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write (N,) timestamps [s] and (N, 4, 4) poses as a TUM trajectory, atomically."""
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    rows = np.column_stack([timestamps, poses[:, :3, 3], quaternions])
    with atomic_path(path) as tmp:
        np.savetxt(tmp, _printed(rows), fmt="%.9f")


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4)) from a TUM file; ValueError if it is not one."""
    rows = _rows(path, 8, "a TUM trajectory has 8 columns (t x y z qx qy qz qw)")
    return rows[:, 0], poses_from_rows(rows[:, 1:])


def write_kitti(path: Path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) poses as KITTI lines, atomically: the top 3x4 of each matrix, row-major."""
    with atomic_path(path) as tmp:
        np.savetxt(tmp, _printed(poses[:, :3, :].reshape(len(poses), 12)), fmt="%.9f")


def _printed(values: np.ndarray) -> np.ndarray:
    """`values` rounded to the 9 decimals written, with no negative zero: a value that prints as zero has no sign
    (rounding noise, such as a last bit from another process, would otherwise flip it)."""
    return np.round(values, 9) + 0.0


def read_kitti(path: Path) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI file (12 values per line); ValueError if it is not one."""
    rows = _rows(path, 12, "a KITTI trajectory has 12 values per line")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def read_trajectory(path: Path) -> tuple[np.ndarray | None, np.ndarray]:
    """(timestamps or None, (N, 4, 4) poses) from a TUM file (8 columns), a KITTI file (12, no timestamps) or a
    keyframe pose list (`vN x y z qx qy qz qw`, no timestamps; in the order of N).

    Raises:
        ValueError: a missing file, or one that is none of them.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such trajectory file: {path}")
    with path.open() as handle:
        first = next((line for line in handle if line.strip() and not line.startswith("#")), "")
    if first.startswith("v"):
        poses = read_keyframe_poses(path)
        return None, np.stack([poses[key] for key in sorted(poses)])
    try:
        with warnings.catch_warnings():  # an empty file: the error below says it better
            warnings.simplefilter("ignore", UserWarning)
            rows = np.loadtxt(path, comments="#", ndmin=2, max_rows=1)
    except ValueError:
        rows = np.empty((0, 0))
    if rows.shape[1:] == (12,):
        return None, read_kitti(path)
    if rows.shape[1:] == (8,):
        return read_tum(path)
    raise ValueError(f"{path}: not a TUM (8 columns), KITTI (12 values per line) or 'vN x y z qx qy qz qw' trajectory")


def read_transform(path: str | Path) -> np.ndarray:
    """A 4x4 rigid transform written as 4 lines of 4 numbers (e.g. T_target_source.txt).

    Raises:
        ValueError: when the file does not hold a rigid 4x4 matrix.
    """
    T = np.loadtxt(path, dtype=np.float64)
    if T.shape != (4, 4) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{path}: expected a 4x4 homogeneous transform, got shape {T.shape}")
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise ValueError(f"{path}: the rotation block is not orthonormal")
    return T


def read_keyframe_poses(path: str | Path) -> dict[int, np.ndarray]:
    """Lines `vN x y z qx qy qz qw` as {N: T_world_keyframeN} (4x4, metres).

    Raises:
        ValueError: on a malformed line.
    """
    keys, rows = [], []
    for line_no, line in enumerate(Path(path).read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 8 or not fields[0].startswith("v"):
            raise ValueError(f"{path}:{line_no}: expected 'vN x y z qx qy qz qw', got {line!r}")
        try:
            keys.append(int(fields[0][1:]))
            rows.append([float(v) for v in fields[1:]])
        except ValueError as error:
            raise ValueError(f"{path}:{line_no}: {error}") from None
    return dict(zip(keys, poses_from_rows(np.array(rows).reshape(-1, 7))))


def poses_from_rows(rows: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses from (N, 7) rows `x y z qx qy qz qw` (scalar-last quaternions)."""
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if len(rows):
        poses[:, :3, :3] = Rotation.from_quat(rows[:, 3:7]).as_matrix()
    poses[:, :3, 3] = rows[:, :3]
    return poses


def _rows(path: Path, columns: int, expected: str) -> np.ndarray:
    """The numbers of a whitespace-separated file as (N, columns); ValueError naming the file otherwise."""
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as error:
        raise ValueError(f"{path}: not a trajectory file ({error})") from None
    if rows.shape[1] != columns or len(rows) == 0:
        raise ValueError(f"{path}: {expected}, found {rows.shape[1]}")
    return rows
