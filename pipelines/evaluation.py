"""Accuracy against ground truth: ATE after a rigid (SE3) alignment (as `evo_ape --align` computes it), RPE, the
error of one pose, and ground truth matched to a SLAM result's frames."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from sandro_core.geometry import interpolate_poses, rigid_fit, rotation_angle
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


def sweep_end_stamps(frames: Iterable) -> np.ndarray:
    """(F,) [s] the times KISS-ICP's poses (and KISS-SLAM's) refer to, of frames (timestamp, points, per-point
    times): each sweep's latest point, where KISS-ICP deskews to (the stamp for frames without times). sandro-slam's
    refer to the middle of the sweep (`SlamResult.timestamps`)."""
    return np.array([stamp + (float(np.max(times)) if len(times) else 0.0) for stamp, _, times in frames])


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


def revisit_errors(
    estimate: np.ndarray, truth: np.ndarray, radius: float = 5.0, min_travel: float = 50.0
) -> tuple[np.ndarray, np.ndarray]:
    """How well a trajectory joins where it returns: for every pose i within `radius` [m] (true positions) of an
    earlier pose at least `min_travel` [m] of travel back, the error of its pose relative to the nearest such
    pose j, est(j)^-1 est(i) against true(j)^-1 true(i). Returns (indices i, (K, 2) [translation m, rotation deg]).
    An odometry that drifts leaves a gap there; loop closure should close it, and must not open one."""
    from scipy.spatial import cKDTree

    positions = truth[:, :3, 3]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    tree = cKDTree(positions)
    indices, errors = [], []
    for i in range(len(truth)):
        near = [j for j in tree.query_ball_point(positions[i], radius) if travelled[i] - travelled[j] >= min_travel]
        if not near:
            continue
        j = min(near, key=lambda k: np.linalg.norm(positions[k] - positions[i]))
        rotation, translation = pose_errors(
            np.linalg.inv(estimate[j]) @ estimate[i], np.linalg.inv(truth[j]) @ truth[i]
        )
        indices.append(i)
        errors.append((translation, rotation))
    return np.array(indices, dtype=int), np.array(errors).reshape(-1, 2)


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
