"""Trajectory error metrics: ATE after a rigid (SE3) alignment, as `evo_ape --align` computes it, and RPE."""

from __future__ import annotations

import numpy as np


def align_se3(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """4x4 T minimising sum ||T p_est - p_ref||^2 over the positions of (N, 4, 4) poses (Umeyama, no scale)."""
    return rigid_fit(estimate[:, :3, 3], reference[:, :3, 3])


def rigid_fit(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """4x4 T minimising sum ||T p_i - q_i||^2 over (N, 3) points (Umeyama, no scale)."""
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    U, _, Vt = np.linalg.svd((q - mq).T @ (p - mp))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    T = np.eye(4)
    T[:3, :3] = U @ D @ Vt
    T[:3, 3] = mq - T[:3, :3] @ mp
    return T


def ate(estimate: np.ndarray, reference: np.ndarray) -> float:
    """Absolute trajectory error [m]: RMSE of the positions of (N, 4, 4) poses after `align_se3`."""
    if len(estimate) != len(reference) or len(estimate) == 0:
        raise ValueError(
            f"ATE needs two trajectories of the same non-zero length, got {len(estimate)} and {len(reference)}"
        )
    aligned = align_se3(estimate, reference) @ estimate
    return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - reference[:, :3, 3]) ** 2, axis=1))))


def rpe(estimate: np.ndarray, reference: np.ndarray, delta: int = 10) -> float:
    """Relative pose error [m]: RMSE of the translation error of the motion over `delta` frames."""
    if len(estimate) != len(reference):
        raise ValueError(f"RPE needs two trajectories of the same length, got {len(estimate)} and {len(reference)}")
    if len(estimate) <= delta:
        return float("nan")
    errors = []
    for i in range(len(estimate) - delta):
        motion_est = np.linalg.inv(estimate[i]) @ estimate[i + delta]
        motion_ref = np.linalg.inv(reference[i]) @ reference[i + delta]
        errors.append(np.linalg.norm((np.linalg.inv(motion_ref) @ motion_est)[:3, 3]))
    return float(np.sqrt(np.mean(np.square(errors))))


def interpolate_poses(times: np.ndarray, poses: np.ndarray, at: np.ndarray,
                      max_gap: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a timed trajectory at other times: linear in position, spherical-linear in rotation.

    Args:
        times: (M,) [s] of `poses` (M, 4, 4); sorted here if they are not.
        at: (N,) [s] the times wanted.
        max_gap: [s] a time is matched only where the two samples around it are at most this far apart.

    Returns:
        (mask (N,) of the times matched, (K, 4, 4) poses at `at[mask]`).
    """
    from scipy.spatial.transform import Rotation, Slerp

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
