"""SANDRO: correspondence-based global registration (IRLS, Geman-McClure under GNC, splitting strategy)."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from sandro_core import _kernels as K
from sandro_core.config import SandroConfig
from sandro_core.covariance import registration_covariance
from sandro_core.result import RegistrationResult
from sandro_core.splits import correspondence_order, split_indices


def register(source: np.ndarray, target: np.ndarray, config: SandroConfig | None = None) -> RegistrationResult:
    """Estimate T_target_source from putative correspondences, without an initial guess.

    Args:
        source: (N, 3) points in the source frame.
        target: (N, 3) points in the target frame; row i of source and target is one correspondence.
        config: solver parameters; None uses the default `SandroConfig()`.

    Raises:
        ValueError: fewer than 3 correspondences, shapes that differ or are not (N, 3), NaN or inf.
    """
    start = time.perf_counter()
    config = config or SandroConfig()
    src, dst = _validated(source, target)
    n = len(src)
    noise_bound = config.noise_bound or estimate_noise_bound(dst)
    alpha_min = noise_bound**2 if config.alpha_floor else 0.0

    hypotheses: list[tuple[np.ndarray, np.ndarray]] = []
    if config.pruning.enabled:
        candidates, hypotheses = consensus_candidates(src, dst, noise_bound, config)
    else:
        candidates = np.arange(n)
    num_splits = max(1, min(config.num_splits, len(candidates) // config.min_split_size))
    splits = split_indices(src, dst, candidates, num_splits, config.split_strategy, config.seed)

    Rs, ts, own_losses, iterations = [], [], [], []
    for idx in splits:
        R, t, gamma, its, _ = K.gnc_irls(
            src,
            dst,
            idx,
            np.eye(3),
            np.zeros(3),
            config.alpha0 or 0.0,
            alpha_min,
            config.beta,
            config.epsilon,
            config.relative_epsilon,
            config.max_iterations,
        )
        Rs.append(R)
        ts.append(t)
        own_losses.append(gamma)
        iterations.append(its)
    if config.rescore:  # the consensus stage's best hypothesis competes with the splits
        for R, t in hypotheses:
            Rs.append(R)
            ts.append(t)
            iterations.append(0)
    Rs_arr, ts_arr = np.array(Rs), np.array(ts)

    alpha_score = noise_bound**2
    if config.rescore:
        split_losses = K.rescoring_losses(src, dst, Rs_arr, ts_arr, alpha_score)
    else:
        split_losses = np.array(own_losses)
    best = int(np.argmin(split_losses))
    R, t, its = Rs_arr[best], ts_arr[best], iterations[best]

    all_idx = np.arange(n)
    if config.refine:
        R_ref, t_ref, _, refine_its, ok = K.gnc_irls(
            src,
            dst,
            all_idx,
            R,
            t,
            alpha_score,
            alpha_score,
            config.beta,
            config.epsilon,
            True,
            config.max_iterations,
        )
        if ok:
            R, t, its = R_ref, t_ref, its + refine_its

    r2 = K.squared_residuals(src, dst, all_idx, R, t)
    weights = alpha_score**2 / (alpha_score + r2) ** 2
    inliers = np.flatnonzero(r2 <= noise_bound**2)
    covariance = registration_covariance(src[inliers], r2[inliers], weights[inliers])
    valid = len(inliers) >= config.min_inliers and bool(np.all(np.isfinite(covariance)))

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return RegistrationResult(
        transformation=T,
        weights=weights,
        inliers=inliers,
        loss=float(K.gm_loss(r2, alpha_score)),
        covariance=covariance,
        valid=valid,
        split_losses=np.asarray(split_losses, dtype=float),
        iterations=int(its),
        time_s=time.perf_counter() - start,
        noise_bound=float(noise_bound),
    )


def estimate_noise_bound(target: np.ndarray) -> float:
    """A noise bound from the data: the median nearest-neighbour spacing of the target points [m]."""
    distances, _ = cKDTree(target).query(target, k=2)
    spacing = float(np.median(distances[:, 1]))
    if spacing <= 0.0:
        spacing = float(np.mean(distances[:, 1]))
    if spacing <= 0.0:
        spacing = 1e-6 * max(float(np.ptp(target)), 1.0)
    return spacing


def consensus_candidates(
    src: np.ndarray, dst: np.ndarray, noise_bound: float, config: SandroConfig
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Indices of the correspondences that agree with the best rigid hypotheses of the consensus stage,
    and the best hypothesis (R, t) itself (none when no clique of 3 exists).

    Seeds (all correspondences, or a seeded coordinate-hash sample of `max_seeds`) are ranked by how many
    correspondences are length-consistent with them; the best `max_clique_seeds` each grow a clique of
    mutually consistent correspondences; each clique's rigid fit is scored by the correspondences it
    brings within the noise bound. Kept: the correspondences explained by every hypothesis scoring at least
    `keep_ratio` times the best. Falls back to all correspondences when no clique of 3 exists.
    """
    p = config.pruning
    n = len(src)
    srcT, dstT = np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T)
    seeds = correspondence_order(src, dst, config.seed)[: min(n, p.max_seeds)]
    thr = p.pair_threshold * noise_bound
    threaded = len(seeds) * n >= p.threads_above
    degrees = (K.consistency_degrees_parallel if threaded else K.consistency_degrees_serial)(
        centred_single(srcT), centred_single(dstT), seeds, np.float32(thr)
    )
    clique_hypotheses = K.clique_hypotheses_parallel if threaded else K.clique_hypotheses_serial
    ranked = seeds[np.argsort(-degrees, kind="stable")][: p.max_clique_seeds]

    # Seeds are tried best-first in batches. The share of the seeds tried so far that the best hypothesis
    # explains estimates how often a ranked seed belongs to the largest structure; the search stops once
    # missing every seed of a structure at least that common has probability below `miss_probability`.
    Rs, ts, scores = [], [], []
    bound2 = noise_bound**2
    for start in range(0, len(ranked), p.batch_size):
        R_b, t_b, s_b = clique_hypotheses(
            src, dst, srcT, dstT, ranked[start : start + p.batch_size], thr, p.max_set_size, noise_bound
        )
        Rs.append(R_b)
        ts.append(t_b)
        scores.append(s_b)
        best = int(np.argmax(np.concatenate(scores)))
        tried = ranked[: start + len(s_b)]
        R_best, t_best = np.concatenate(Rs)[best], np.concatenate(ts)[best]
        share = np.mean(K.squared_residuals(src, dst, tried, R_best, t_best) <= bound2)
        if share >= 1.0 or len(tried) * np.log1p(-share) < np.log(p.miss_probability):
            break
    Rs, ts, scores = np.concatenate(Rs), np.concatenate(ts), np.concatenate(scores)
    if scores.max() < 3:
        return np.arange(n), []
    keep = np.flatnonzero(scores >= p.keep_ratio * scores.max())
    explained = np.zeros(n, dtype=bool)
    all_idx = np.arange(n)
    for h in keep:
        explained |= K.squared_residuals(src, dst, all_idx, Rs[h], ts[h]) <= noise_bound**2
    best = int(np.argmax(scores))
    return np.flatnonzero(explained), [(Rs[best], ts[best])]


def centred_single(pointsT: np.ndarray) -> np.ndarray:
    """(3, N) points moved to their centroid, in float32: lengths between them keep ~1e-7 of the scene's
    extent wherever it lies (map coordinates 1e5 m from the origin would leave metres-size gaps ~1e-2 m)."""
    return (pointsT - pointsT.mean(axis=1, keepdims=True)).astype(np.float32)


def _validated(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src = np.ascontiguousarray(source, dtype=np.float64)
    dst = np.ascontiguousarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"source must be an (N, 3) array, got shape {src.shape}")
    if dst.ndim != 2 or dst.shape[1] != 3:
        raise ValueError(f"target must be an (N, 3) array, got shape {dst.shape}")
    if len(src) != len(dst):
        raise ValueError(f"source and target must have the same number of rows, got {len(src)} and {len(dst)}")
    if len(src) < 3:
        raise ValueError(f"at least 3 correspondences are needed, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("source and target must not contain NaN or inf")
    return src, dst
