"""Readers for ground-truth transforms of the registration pair data sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def load_transform(path: str | Path) -> np.ndarray:
    """Read a 4x4 transform written as 4 lines of 4 numbers (e.g. T_target_source.txt).

    Raises:
        ValueError: when the file does not hold a rigid 4x4 matrix.
    """
    T = np.loadtxt(path, dtype=np.float64)
    if T.shape != (4, 4) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{path}: expected a 4x4 homogeneous transform, got shape {T.shape}")
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise ValueError(f"{path}: the rotation block is not orthonormal")
    return T


def load_keyframe_poses(path: str | Path) -> dict[int, np.ndarray]:
    """Read lines `vN x y z qx qy qz qw` into {N: T_world_keyframeN} (4x4, metres).

    Raises:
        ValueError: on a malformed line.
    """
    poses: dict[int, np.ndarray] = {}
    for line_no, line in enumerate(Path(path).read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 8 or not fields[0].startswith("v"):
            raise ValueError(f"{path}:{line_no}: expected 'vN x y z qx qy qz qw', got {line!r}")
        try:
            key = int(fields[0][1:])
            values = np.array([float(v) for v in fields[1:]])
        except ValueError as error:
            raise ValueError(f"{path}:{line_no}: {error}") from None
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(values[3:]).as_matrix()  # scalar-last: qx qy qz qw
        T[:3, 3] = values[:3]
        poses[key] = T
    return poses
