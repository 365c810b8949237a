"""Synthetic correspondence problems with known ground truth, for tests and benchmarks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from sandro_core.geometry import transform_points

OutlierKind = Literal["uniform", "structured"]


@dataclass(frozen=True)
class SyntheticProblem:
    """Putative correspondences: row i of `source` and `target` is one correspondence."""

    source: np.ndarray  # (N, 3) source points [m]
    target: np.ndarray  # (N, 3) target points [m]
    T_target_source: np.ndarray  # 4x4 ground truth
    inlier_mask: np.ndarray  # (N,) True where target[i] = T source[i] + noise
    noise_bound: float  # [m], the bound handed to solvers
    noise_sigma: float  # [m], per-axis standard deviation of the inlier noise


def random_transform(rng: np.random.Generator, max_translation: float) -> np.ndarray:
    """A 4x4 rigid transform with a uniformly random rotation and a translation of norm <= max_translation."""
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(0.0, max_translation)
    return T


def make_problem(
    rng: np.random.Generator,
    n: int = 1000,
    outlier_rate: float = 0.9,
    outlier_kind: OutlierKind = "uniform",
    noise_sigma: float = 0.01,
    noise_bound: float = 0.05,
    max_translation: float = 10.0,
    structured_ratio: tuple[float, float] = (0.5, 0.9),
    cloud: np.ndarray | None = None,
) -> SyntheticProblem:
    """Correspondences between a cloud and its moved, noisy copy, with a given share of outliers.

    The source points are `cloud` (rows drawn at random) or uniform in a 1 m cube centred at the origin.
    Inliers: target = T source + N(0, noise_sigma^2 I). Uniform outliers: target drawn uniformly in the
    target's bounding box. Structured outliers (the symmetric-scene case): a coherent cluster, with
    `structured_ratio` times as many points as the inliers, consistent with one wrong rigid transform that
    maps the source into the same region of the target; the rest of the outliers are uniform.
    """
    if not 0.0 <= outlier_rate < 1.0:
        raise ValueError(f"outlier_rate must be in [0, 1), got {outlier_rate}")
    if cloud is None:
        source = rng.uniform(-0.5, 0.5, size=(n, 3))
    else:
        source = cloud[rng.choice(len(cloud), size=n, replace=len(cloud) < n)].astype(np.float64)
    T = random_transform(rng, max_translation)
    target = transform_points(T, source) + rng.normal(scale=noise_sigma, size=(n, 3))

    n_outliers = int(round(outlier_rate * n))
    outliers = rng.choice(n, size=n_outliers, replace=False)
    n_structured = 0
    if outlier_kind == "structured":
        n_inliers = n - n_outliers
        n_structured = min(n_outliers, int(round(rng.uniform(*structured_ratio) * n_inliers)))
        centre = source.mean(axis=0)
        wrong = np.eye(4)
        axis = rng.normal(size=3)
        angle = rng.uniform(np.pi / 2, np.pi)
        wrong[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
        wrong[:3, 3] = centre - wrong[:3, :3] @ centre  # rotate about the centroid: same region
        T_wrong = T @ wrong
        idx = outliers[:n_structured]
        target[idx] = transform_points(T_wrong, source[idx]) + rng.normal(scale=noise_sigma, size=(n_structured, 3))
    elif outlier_kind != "uniform":
        raise ValueError(f"unknown outlier kind {outlier_kind!r}")
    uniform_idx = outliers[n_structured:]
    lo, hi = target.min(axis=0), target.max(axis=0)
    target[uniform_idx] = rng.uniform(lo, hi, size=(len(uniform_idx), 3))

    inlier_mask = np.ones(n, dtype=bool)
    inlier_mask[outliers] = False
    return SyntheticProblem(source, target, T, inlier_mask, noise_bound, noise_sigma)
