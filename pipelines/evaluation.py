"""Accuracy against ground truth: ATE after a rigid (SE3) alignment (as `evo_ape --align` computes it), RPE, the
error of one pose, and ground truth matched to a SLAM result's frames."""

from __future__ import annotations

import numpy as np

from sandro_core.geometry import rigid_fit, rotation_angle
from sandro_slam import SlamResult


def align_se3(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """4x4 T minimising sum ||T p_est - p_ref||^2 over the positions of (N, 4, 4) poses (Umeyama, no scale)."""
    return rigid_fit(estimate[:, :3, 3], reference[:, :3, 3])


def pose_errors(T_estimate: np.ndarray, T_truth: np.ndarray) -> tuple[float, float]:
    """Rotation error [deg] (the angle of R_est^T R_true) and translation error [m] (|t_est - t_true|)."""
    angle = np.degrees(rotation_angle(T_estimate[:3, :3].T @ T_truth[:3, :3]))
    return float(angle), float(np.linalg.norm(T_estimate[:3, 3] - T_truth[:3, 3]))


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


def match_ground_truth(
    result: SlamResult, times: np.ndarray | None, poses: np.ndarray, max_gap: float = 0.25
) -> tuple[np.ndarray, np.ndarray]:
    """(mask of the result's frames with a ground-truth pose, those poses). TUM ground truth (with `times`) is
    interpolated at the result's pose times, not across gaps longer than `max_gap` [s]; KITTI ground truth (no
    times) is taken as one pose per input frame, in order (skipped frames included)."""
    if times is not None:
        return interpolate_poses(times, poses, result.timestamps, max_gap)
    skipped = set(result.skipped_frames)
    read = len(result.timestamps) + len(skipped)
    indices = np.array([i for i in range(read) if i not in skipped], dtype=int)
    mask = indices < len(poses)
    return mask, poses[indices[mask]]


def evaluate(result: SlamResult, mask: np.ndarray, truth: np.ndarray) -> dict:
    """ATE [m] (RMSE after an SE3 alignment) and RPE [m] over 10 frames, before and after loop closure, on the
    frames in `mask` against their ground-truth poses `truth` (as `match_ground_truth` returns them).

    Raises:
        ValueError: the ground truth covers fewer than 3 of the frames.
    """
    if mask.sum() < 3:
        raise ValueError("the ground truth covers fewer than 3 of the processed scans (check its times or format)")
    metrics = {"frames_matched": int(mask.sum())}
    for name, estimate in (("odometry", result.odometry_poses[mask]), ("slam", result.poses[mask])):
        metrics[f"ate_{name}_m"] = ate(estimate, truth)
        metrics[f"rpe_{name}_m"] = rpe(estimate, truth)
    return metrics
