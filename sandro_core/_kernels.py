"""Compiled inner loops of the solver (numba). All of them use O(N) memory.

Notation: `src` (N,3) source points q_i, `dst` (N,3) target points p_i, residual r_i = p_i - (R q_i + t).
`alpha` is a squared length [m^2].
"""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # The TBB that other wheels (open3d) bring is often too old for numba and only warns: prefer OpenMP.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


@njit(cache=True)
def weighted_kabsch(src, dst, idx, w):
    """Weighted least-squares rigid transform over src[idx] -> dst[idx] (weighted SVD).

    Returns (R, t, ok); ok is False when the weights vanish.
    """
    sw = 0.0
    cs = np.zeros(3)
    cd = np.zeros(3)
    for k in range(idx.shape[0]):
        i = idx[k]
        wk = w[k]
        sw += wk
        for a in range(3):
            cs[a] += wk * src[i, a]
            cd[a] += wk * dst[i, a]
    if sw <= 1e-300:
        return np.eye(3), np.zeros(3), False
    cs /= sw
    cd /= sw
    H = np.zeros((3, 3))
    for k in range(idx.shape[0]):
        i = idx[k]
        wk = w[k]
        for a in range(3):
            qa = wk * (src[i, a] - cs[a])
            for b in range(3):
                H[a, b] += qa * (dst[i, b] - cd[b])
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0.0:
        D = np.eye(3)
        D[2, 2] = -1.0
        R = Vt.T @ D @ U.T
    t = cd - R @ cs
    return R, t, True


@njit(cache=True)
def squared_residuals(src, dst, idx, R, t):
    """||p_i - (R q_i + t)||^2 for i in idx."""
    out = np.empty(idx.shape[0])
    for k in range(idx.shape[0]):
        i = idx[k]
        s = 0.0
        for a in range(3):
            e = dst[i, a] - (R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a])
            s += e * e
        out[k] = s
    return out


@njit(cache=True)
def gm_loss(r2, alpha):
    """Geman-McClure loss sum_i alpha r_i^2 / (alpha + r_i^2) [m^2]."""
    s = 0.0
    for k in range(r2.shape[0]):
        s += alpha * r2[k] / (alpha + r2[k])
    return s


@njit(cache=True)
def gnc_irls(src, dst, idx, R0, t0, alpha0, alpha_min, beta, epsilon, relative, max_iterations):
    """SANDRO's IRLS with the Geman-McClure loss under graduated non-convexity (Algorithm 1).

    Each iteration: residuals, weights w = alpha^2 / (alpha + r^2)^2, loss gamma = sum r^2 / (alpha + r^2),
    weighted SVD, alpha <- max(alpha * beta, alpha_min). Stops when |gamma - gamma_prev| < epsilon
    (relative to gamma when `relative`; then only once alpha has reached alpha_min).
    alpha0 <= 0 means: start from the largest squared residual at (R0, t0).

    Returns (R, t, gamma, iterations, ok).
    """
    R = R0.copy()
    t = t0.copy()
    alpha = alpha0
    if alpha <= 0.0:
        alpha = max(np.max(squared_residuals(src, dst, idx, R, t)), alpha_min, 1e-12)
    gamma_prev = np.inf
    gamma = np.inf
    it = 0
    ok = True
    w = np.empty(idx.shape[0])
    while it < max_iterations:
        r2 = squared_residuals(src, dst, idx, R, t)
        gamma = 0.0
        for k in range(r2.shape[0]):
            d = alpha + r2[k]
            w[k] = alpha * alpha / (d * d)
            gamma += r2[k] / d
        R_new, t_new, ok = weighted_kabsch(src, dst, idx, w)
        it += 1
        if not ok:
            break
        R, t = R_new, t_new
        at_floor = alpha <= alpha_min
        alpha = max(alpha * beta, alpha_min)
        change = abs(gamma - gamma_prev)
        if relative:
            if at_floor and change < epsilon * max(gamma, 1e-12):
                break
        elif change < epsilon:
            break
        gamma_prev = gamma
    return R, t, gamma, it, ok


@njit(cache=True, fastmath=True)
def _length_gaps(srcT, dstT, i, out):
    """out[j] = | ||p_i - p_j|| - ||q_i - q_j|| | for every j. srcT/dstT are (3, N) so the loop vectorises."""
    s0, s1, s2 = srcT[0, i], srcT[1, i], srcT[2, i]
    d0, d1, d2 = dstT[0, i], dstT[1, i], dstT[2, i]
    for j in range(srcT.shape[1]):
        a0 = srcT[0, j] - s0
        a1 = srcT[1, j] - s1
        a2 = srcT[2, j] - s2
        b0 = dstT[0, j] - d0
        b1 = dstT[1, j] - d1
        b2 = dstT[2, j] - d2
        out[j] = abs(np.sqrt(b0 * b0 + b1 * b1 + b2 * b2) - np.sqrt(a0 * a0 + a1 * a1 + a2 * a2))


@njit(cache=True, fastmath=True)
def _consistent(srcT, dstT, i, j, thr):
    a = 0.0
    b = 0.0
    for k in range(3):
        e = srcT[k, i] - srcT[k, j]
        f = dstT[k, i] - dstT[k, j]
        a += e * e
        b += f * f
    return abs(np.sqrt(b) - np.sqrt(a)) <= thr


def consistency_degrees(srcT, dstT, seeds, thr):
    """For each seed, how many other correspondences are length-consistent with it. O(M N) time.

    The degrees only rank the seeds: the caller passes float32 points, centred (`registration.centred_single`),
    on which the loop takes twice the SIMD lanes of float64."""
    n = srcT.shape[1]
    deg = np.zeros(seeds.shape[0], dtype=np.int64)
    for k in prange(seeds.shape[0]):
        gaps = np.empty(n, dtype=srcT.dtype)
        _length_gaps(srcT, dstT, seeds[k], gaps)
        count = 0
        for j in range(n):
            if gaps[j] <= thr:
                count += 1
        deg[k] = count - 1
    return deg


@njit(cache=True)
def seed_clique(srcT, dstT, seed, thr, max_set):
    """A large clique of mutually consistent correspondences containing `seed`.

    The seed's consistent set (its `max_set - 1` most consistent members) is peeled: the member with the
    fewest consistent partners inside the set goes first, until every remaining pair is consistent.
    Memory: O(N + max_set^2).
    """
    gaps = np.empty(srcT.shape[1])
    _length_gaps(srcT, dstT, seed, gaps)
    gaps[seed] = np.inf
    members = np.flatnonzero(gaps <= thr)
    if members.shape[0] > max_set - 1:  # keep the most consistent ones
        members = members[np.argsort(gaps[members])[: max_set - 1]]
    s = members.shape[0] + 1
    sel = np.empty(s, dtype=np.int64)
    sel[0] = seed
    sel[1:] = members
    adj = np.zeros((s, s), dtype=np.bool_)
    deg = np.zeros(s, dtype=np.int64)
    deg[0] = s - 1
    for a in range(1, s):
        adj[0, a] = True
        adj[a, 0] = True
        deg[a] += 1
        for b in range(a + 1, s):
            if _consistent(srcT, dstT, sel[a], sel[b], thr):
                adj[a, b] = True
                adj[b, a] = True
                deg[a] += 1
                deg[b] += 1
    alive = np.ones(s, dtype=np.bool_)
    size = s
    while size > 1:
        worst = -1
        worst_deg = s + 1
        for a in range(1, s):
            if alive[a] and deg[a] < worst_deg:
                worst_deg = deg[a]
                worst = a
        if worst_deg >= size - 1:
            break
        alive[worst] = False
        size -= 1
        for b in range(s):
            if alive[b] and adj[worst, b]:
                deg[b] -= 1
    out = np.empty(size, dtype=np.int64)
    c = 0
    for a in range(s):
        if alive[a]:
            out[c] = sel[a]
            c += 1
    return out


def clique_hypotheses(src, dst, srcT, dstT, seeds, thr, max_set, inlier_bound):
    """One rigid hypothesis per seed: the Kabsch fit of its clique, scored by how many of all
    correspondences it brings within `inlier_bound`. Returns (Rs, ts, scores)."""
    m = seeds.shape[0]
    n = src.shape[0]
    Rs = np.zeros((m, 3, 3))
    ts = np.zeros((m, 3))
    scores = np.zeros(m, dtype=np.int64)
    all_idx = np.arange(n)
    bound2 = inlier_bound * inlier_bound
    for k in prange(m):
        clique = seed_clique(srcT, dstT, seeds[k], thr, max_set)
        if clique.shape[0] < 3:
            continue
        R, t, ok = weighted_kabsch(src, dst, clique, np.ones(clique.shape[0]))
        if not ok:
            continue
        Rs[k] = R
        ts[k] = t
        r2 = squared_residuals(src, dst, all_idx, R, t)
        scores[k] = np.sum(r2 <= bound2)
    return Rs, ts, scores


# Threads pay off only on large problems; on small ones, and beside other busy threads (the OpenMP
# barrier then waits for a descheduled thread), they cost up to 15x: both variants are compiled.
consistency_degrees_serial = njit(cache=True)(consistency_degrees)
consistency_degrees_parallel = njit(cache=True, parallel=True)(consistency_degrees)
clique_hypotheses_serial = njit(cache=True)(clique_hypotheses)
clique_hypotheses_parallel = njit(cache=True, parallel=True)(clique_hypotheses)


@njit(cache=True)
def rescoring_losses(src, dst, Rs, ts, alpha):
    """Geman-McClure loss at scale alpha of each candidate transform over all correspondences."""
    all_idx = np.arange(src.shape[0])
    out = np.empty(Rs.shape[0])
    for k in range(Rs.shape[0]):
        out[k] = gm_loss(squared_residuals(src, dst, all_idx, Rs[k], ts[k]), alpha)
    return out
