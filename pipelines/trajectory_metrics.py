"""Trajectory error metrics: ATE after a rigid (SE3) alignment, as `evo_ape --align` computes it, and RPE."""

from __future__ import annotations

import numpy as np


def align_se3(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """4x4 T minimising sum ||T p_est - p_ref||^2 over the positions (Umeyama, no scale)."""
    p, q = estimate[:, :3, 3], reference[:, :3, 3]
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
        raise ValueError(f"ATE needs two trajectories of the same non-zero length, got {len(estimate)} and {len(reference)}")
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
