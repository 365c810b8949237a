"""The result of a registration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RegistrationResult:
    """What `sandro_core.register` returns.

    Attributes:
        transformation: 4x4 T_target_source, maps source points onto target points.
        weights: (N,) final IRLS weights in [0, 1], one per correspondence.
        inliers: indices of the correspondences whose residual is within the noise bound.
        loss: Geman-McClure loss of `transformation` over all correspondences, at alpha = noise_bound^2 [m^2].
        covariance: 6x6 covariance of `transformation` in gtsam Pose3 order [rotation, translation],
            for a right (body-frame) perturbation: T_true = T_est * Exp(xi), xi ~ N(0, covariance).
            All NaN when the geometry leaves the transform unobservable.
        valid: False when too few inliers remain or the inlier geometry is degenerate.
        split_losses: per split, the loss used to pick the winner (on all correspondences when
            rescoring is on, on the split's own correspondences otherwise); with rescoring and the
            consensus stage on, a last entry scores the consensus stage's best hypothesis.
        iterations: IRLS iterations of the winning split (plus refinement).
        time_s: wall-clock time of the call [s].
        noise_bound: the noise bound that was used [m].
    """

    transformation: np.ndarray
    weights: np.ndarray
    inliers: np.ndarray
    loss: float
    covariance: np.ndarray
    valid: bool
    split_losses: np.ndarray
    iterations: int
    time_s: float
    noise_bound: float
