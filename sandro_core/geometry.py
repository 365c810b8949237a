"""Rigid-transform helpers shared by every layer. Transforms are 4x4 arrays; points are (N, 3) [m]."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The (N, 3) `points` mapped by the 4x4 transform T (T_target_source maps source points into the target)."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle(R: np.ndarray) -> np.ndarray | float:
    """Angle [rad] of a 3x3 rotation matrix, or of each of a stack (..., 3, 3) of them."""
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return float(angle) if np.ndim(angle) == 0 else angle


def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 rigid T minimising sum_i w_i ||T source_i - target_i||^2 (Kabsch/Umeyama without scale).

    Args:
        source, target: (N, 3) corresponding points [m].
        weights: (N,) non-negative, not all zero; None: all 1.
    """
    weights = np.ones(len(source)) if weights is None else weights
    total = weights.sum()
    source_mean = weights @ source / total
    target_mean = weights @ target / total
    cross = (source - source_mean).T @ ((target - target_mean) * weights[:, None])  # sum_i w_i q_i p_i^T
    u, _, vt = np.linalg.svd(cross)
    reflection = np.sign(np.linalg.det(vt.T @ u.T))
    T = np.eye(4)
    T[:3, :3] = vt.T @ np.diag([1.0, 1.0, reflection]) @ u.T
    T[:3, 3] = target_mean - T[:3, :3] @ source_mean
    return T


def interpolate_poses(
    times: np.ndarray, poses: np.ndarray, at: np.ndarray, max_gap: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a timed trajectory at other times: linear in position, spherical-linear in rotation.

    Args:
        times: (M,) [s] of `poses` (M, 4, 4); sorted here if they are not.
        at: (N,) [s] the times wanted.
        max_gap: [s] a time is matched only where the two samples around it are at most this far apart.

    Returns:
        (mask (N,) of the times matched, (K, 4, 4) poses at `at[mask]`).
    """
    order = np.argsort(times, kind="stable")
    times, poses = np.asarray(times)[order], np.asarray(poses)[order]
    if len(times) < 2:
        return np.zeros(len(at), dtype=bool), np.empty((0, 4, 4))
    upper = np.clip(np.searchsorted(times, at, side="left"), 1, len(times) - 1)
    inside = (at >= times[0]) & (at <= times[-1])
    mask = inside & (times[upper] - times[upper - 1] <= max_gap)
    wanted = at[mask]
    out = np.tile(np.eye(4), (len(wanted), 1, 1))
    if len(wanted):
        lo, hi = upper[mask] - 1, upper[mask]
        span = times[hi] - times[lo]
        s = np.divide(wanted - times[lo], span, out=np.zeros_like(wanted), where=span > 0)
        out[:, :3, 3] = (1 - s)[:, None] * poses[lo, :3, 3] + s[:, None] * poses[hi, :3, 3]
        out[:, :3, :3] = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(wanted).as_matrix()
    return mask, out
