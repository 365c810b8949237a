"""Covariance of a registration from its final IRLS weights."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices [v]x."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def registration_information(source: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """H = sum_i w_i J_i^T J_i for residuals r_i = p_i - T Exp(xi) q_i, xi = [rotation, translation].

    J_i = [R [q_i]x, -R]; R cancels in J_i^T J_i, so H depends on the source points and weights only:
    H = sum_i w_i [[[q_i]x^T [q_i]x, [q_i]x], [-[q_i]x, I]].
    """
    w = weights[:, None, None]
    Q = skew(source)
    H = np.zeros((6, 6))
    H[:3, :3] = np.sum(w * np.einsum("nji,njk->nik", Q, Q), axis=0)
    H[:3, 3:] = np.sum(w * Q, axis=0)
    H[3:, :3] = -H[:3, 3:]
    H[3:, 3:] = np.eye(3) * weights.sum()
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
