"""gtsam factors and noise models in the project's conventions: covariances in gtsam Pose3 order [rotation,
translation], for a right (body-frame) perturbation."""

from __future__ import annotations

from collections.abc import Iterable

import gtsam
import numpy as np

from sandro_slam.config import GraphConfig


def between_factor(key_a: int, key_b: int, T_a_b: np.ndarray, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """BetweenFactorPose3 measuring T_a_b, with a 6x6 covariance of its right (body-frame) perturbation."""
    return gtsam.BetweenFactorPose3(key_a, key_b, gtsam.Pose3(T_a_b), gtsam.noiseModel.Gaussian.Covariance(covariance))


def gaussian_noise(factor: gtsam.NoiseModelFactor) -> gtsam.noiseModel.Base:
    """A factor's noise model, or the Gaussian a robust model wraps."""
    model = factor.noiseModel()
    return model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model


def scaled_noise(factor: gtsam.BetweenFactorPose3, scale: float) -> gtsam.BetweenFactorPose3:
    """The same factor with its (Gaussian) covariance times `scale`."""
    covariance = np.asarray(gaussian_noise(factor).covariance()) * scale
    return between_factor(factor.keys()[0], factor.keys()[1], factor.measured().matrix(), covariance)


def keyframe_odometry_covariances(odometry: Iterable[tuple[int, int, np.ndarray]]) -> dict[int, np.ndarray]:
    """Per keyframe key, the 6x6 covariance of the odometry factor across its keyframe: the one that ends at it (the
    first keyframe: the one that starts at it). `odometry`: (from key, to key, covariance) in driving order."""
    covariances: dict[int, np.ndarray] = {}
    for start, end, covariance in odometry:
        covariances[end] = covariance
        covariances.setdefault(start, covariance)
    return covariances


def widened_loop_covariance(covariance: np.ndarray, *keyframe_odometry: np.ndarray | None) -> np.ndarray:
    """A loop's 6x6 covariance plus the odometry covariance across each of its two keyframes (None: none known): a
    loop aligns two submaps, each only as rigid as the odometry that built it (`GraphConfig.loop_submap_noise`)."""
    return covariance + sum((c for c in keyframe_odometry if c is not None), np.zeros((6, 6)))


def odometry_covariance(distance: float, config: GraphConfig) -> np.ndarray:
    """6x6 covariance of an odometry factor over `distance` metres: std growing linearly with travel."""
    rot = config.odometry_rotation_sigma_per_m * distance + config.odometry_sigma_floor
    trans = config.odometry_translation_sigma_per_m * distance + config.odometry_sigma_floor
    return np.diag([rot**2] * 3 + [trans**2] * 3)
