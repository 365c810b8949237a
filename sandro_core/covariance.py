"""Covariance of a registration from its final IRLS weights."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """A 3-vector -> its cross-product matrix [v]x."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def registration_information(source: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """H = sum_i w_i J_i^T J_i for residuals r_i = p_i - T Exp(xi) q_i, xi = [rotation, translation].

    J_i = [R [q_i]x, -R]; R cancels in J_i^T J_i, so H depends on the source points and weights only:
    H = sum_i w_i [[[q_i]x^T [q_i]x, [q_i]x], [-[q_i]x, I]], with [q]x^T [q]x = |q|^2 I - q q^T.
    """
    sw = weights.sum()
    wq = weights @ source
    wqq = (source * weights[:, None]).T @ source
    H = np.zeros((6, 6))
    H[:3, :3] = np.trace(wqq) * np.eye(3) - wqq
    H[:3, 3:] = skew(wq)
    H[3:, :3] = -H[:3, 3:]
    H[3:, 3:] = sw * np.eye(3)
    return H


def registration_covariance(source: np.ndarray, squared_residuals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Sigma = sigma^2 H^-1 in gtsam Pose3 order [rotation, translation], right (body-frame) perturbation.

    sigma^2 (per axis) is estimated from the weighted residuals: sum w r^2 / (3 sum w - 6).
    Returns an all-NaN matrix when H is singular (degenerate geometry) or too few weights remain.
    """
    dof = 3.0 * weights.sum() - 6.0
    H = registration_information(source, weights)
    if dof <= 0.0 or not _well_conditioned(H):
        return np.full((6, 6), np.nan)
    sigma2 = float(weights @ squared_residuals) / dof
    cov = sigma2 * np.linalg.inv(H)
    return 0.5 * (cov + cov.T)


def _well_conditioned(H: np.ndarray, max_condition: float = 1e12) -> bool:
    eig = np.linalg.eigvalsh(H)
    return bool(eig[0] > 0.0 and eig[-1] / eig[0] < max_condition)
