"""Baseline robust registration solvers on putative correspondences, for benchmarks.

Every solver has the call shape `fn(source, target, noise_bound) -> T_target_source`: `source` and
`target` are (N, 3) arrays [m] whose row i is one correspondence (source point in the source frame,
target point in the target frame), `noise_bound` [m] is the largest residual ||target - T source|| of
an inlier, and the 4x4 result maps source points into the target frame.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
import open3d as o3d

from sandro_core.geometry import rigid_fit, transform_points
from sandro_slam.loop_registration import open3d_on_one_thread

try:
    import kiss_matcher as _kiss_matcher
except ImportError:  # optional: `pip install kiss-matcher`
    _kiss_matcher = None

Solver = Callable[[np.ndarray, np.ndarray, float], np.ndarray]

OPEN3D_SEED = 0  # Open3D's global RNG is reseeded with this before every RANSAC / FGR call
GNC_MU_FACTOR = 1.4  # mu <- mu * factor per GNC iteration (Yang et al. 2020)
GNC_MAX_ITERATIONS = 100
GNC_WEIGHT_TOLERANCE = 1e-6  # stop when no weight changes by more than this


def _check(source: np.ndarray, target: np.ndarray, noise_bound: float) -> tuple[np.ndarray, np.ndarray]:
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.ndim != 2 or source.shape[1] != 3 or source.shape != target.shape:
        raise ValueError(f"source and target must both be (N, 3), got {source.shape} and {target.shape}")
    if len(source) < 3:
        raise ValueError(f"at least 3 correspondences are needed, got {len(source)}")
    if not (np.all(np.isfinite(source)) and np.all(np.isfinite(target))):
        raise ValueError("source or target contains NaN or infinite coordinates")
    if not (np.isfinite(noise_bound) and noise_bound > 0.0):
        raise ValueError(f"noise_bound must be a positive finite number [m], got {noise_bound}")
    return source, target


def _open3d_inputs(
    source: np.ndarray, target: np.ndarray
) -> tuple[o3d.geometry.PointCloud, o3d.geometry.PointCloud, o3d.utility.Vector2iVector]:
    index = np.arange(len(source), dtype=np.int32)
    return (
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)),
        o3d.utility.Vector2iVector(np.column_stack([index, index])),
    )


def _ransac(source: np.ndarray, target: np.ndarray, noise_bound: float, max_iteration: int) -> np.ndarray:
    """Open3D's threads draw samples from one shared RNG, so the seed alone does not fix the result:
    it runs single-threaded (on 2 cores measured no slower, the shared RNG being contended anyway)."""
    source, target = _check(source, target, noise_bound)
    registration = o3d.pipelines.registration
    with open3d_on_one_thread():
        o3d.utility.random.seed(OPEN3D_SEED)
        result = registration.registration_ransac_based_on_correspondence(
            *_open3d_inputs(source, target),
            max_correspondence_distance=noise_bound,
            estimation_method=registration.TransformationEstimationPointToPoint(False),
            ransac_n=3,
            checkers=[
                registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                registration.CorrespondenceCheckerBasedOnDistance(noise_bound),
            ],
            criteria=registration.RANSACConvergenceCriteria(max_iteration=max_iteration, confidence=0.999),
        )
    return np.array(result.transformation)


def ransac_1e3(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """Open3D RANSAC on correspondences, 3-point samples, at most 1e3 iterations (confidence 0.999)."""
    return _ransac(source, target, noise_bound, 1_000)


def ransac_1e5(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """Open3D RANSAC on correspondences, 3-point samples, at most 1e5 iterations (confidence 0.999)."""
    return _ransac(source, target, noise_bound, 100_000)


def fgr(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """Open3D Fast Global Registration on correspondences, graduated non-convexity on (decrease_mu).

    Open3D's other FGR options keep their defaults (scale normalisation, tuple test, 64 iterations).
    """
    source, target = _check(source, target, noise_bound)
    registration = o3d.pipelines.registration
    option = registration.FastGlobalRegistrationOption(maximum_correspondence_distance=noise_bound, decrease_mu=True)
    o3d.utility.random.seed(OPEN3D_SEED)
    result = registration.registration_fgr_based_on_correspondence(*_open3d_inputs(source, target), option)
    return np.array(result.transformation)


def _squared_residuals(T: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    return np.sum((transform_points(T, source) - target) ** 2, axis=1)


def gnc_tls(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """Graduated non-convexity with a truncated least squares cost (GNC-TLS, Yang et al. 2020).

    Minimises sum_i min(r_i^2, c^2) with c = noise_bound through the surrogate rho_mu, mu growing from
    c^2 / (2 r_max^2 - c^2) (nearly convex) by a factor 1.4 per iteration towards TLS. Each iteration is
    a weighted rigid fit followed by the closed-form weight update
        w_i = 1                                  if r_i^2 <= mu / (mu + 1) c^2,
        w_i = c / r_i sqrt(mu (mu + 1)) - mu      in between,
        w_i = 0                                  if r_i^2 >= (mu + 1) / mu c^2.
    Stops when no weight changes by more than 1e-6, after 100 iterations, or when fewer than 3
    correspondences keep a non-zero weight (the last fit is returned then).
    """
    source, target = _check(source, target, noise_bound)
    c2 = noise_bound**2
    weights = np.ones(len(source))
    T = rigid_fit(source, target, weights)
    r2 = _squared_residuals(T, source, target)
    if r2.max() <= c2:
        return T
    mu = c2 / (2.0 * r2.max() - c2)
    for _ in range(GNC_MAX_ITERATIONS):
        lower, upper = mu / (mu + 1.0) * c2, (mu + 1.0) / mu * c2
        middle = np.sqrt(c2 * mu * (mu + 1.0) / np.maximum(r2, 1e-300)) - mu
        new_weights = np.where(r2 <= lower, 1.0, np.where(r2 >= upper, 0.0, middle))
        if np.count_nonzero(new_weights) < 3:
            break
        converged = np.max(np.abs(new_weights - weights)) <= GNC_WEIGHT_TOLERANCE
        weights = new_weights
        T = rigid_fit(source, target, weights)
        if converged:
            break
        r2 = _squared_residuals(T, source, target)
        mu *= GNC_MU_FACTOR
    return T


def kiss_matcher(source: np.ndarray, target: np.ndarray, noise_bound: float, pruning_factor: float = 1.0) -> np.ndarray:
    """KISS-Matcher's `prune_and_solve`: ROBIN max-core pruning, then its GNC-TLS solver.

    The solver's inlier bound is `noise_bound`, the pruning bound (pairwise length consistency)
    `pruning_factor * noise_bound`; its voxel size only drives its own feature extraction, unused here.
    Needs the optional package `kiss-matcher`.
    """
    source, target = _check(source, target, noise_bound)
    if _kiss_matcher is None:
        raise ImportError("kiss_matcher is not installed: pip install kiss-matcher")
    # voxel_size only sets its feature radii (unused here), but must be >= 5 mm
    config = _kiss_matcher.KISSMatcherConfig(voxel_size=max(noise_bound, 0.01), enable_noise_bound_clamping=False)
    config.robin_noise_bound = pruning_factor * noise_bound
    config.solver_noise_bound = noise_bound
    solution = _kiss_matcher.KISSMatcher(config).prune_and_solve(source.astype(np.float32), target.astype(np.float32))
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation)
    T[:3, 3] = np.asarray(solution.translation).ravel()
    return T


BASELINES: dict[str, Solver] = {
    "ransac_1e3": ransac_1e3,
    "ransac_1e5": ransac_1e5,
    "fgr": fgr,
    "gnc_tls": gnc_tls,
}
if _kiss_matcher is not None:
    BASELINES["kiss_matcher"] = kiss_matcher
    # A tighter pruning bound suits the synthetic sweep better (20/20 instead of 4/20 at 95 % outliers).
    BASELINES["kiss_matcher_0.5c"] = partial(kiss_matcher, pruning_factor=0.5)
