"""Compiled inner loops of the solver (numba). All of them use O(N) memory.

Notation: `src` (N,3) source points q_i, `dst` (N,3) target points p_i, residual r_i = p_i - (R q_i + t).
`alpha` is a squared length [m^2].
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


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


@njit(cache=True)
def _consistent(src, dst, i, j, thr):
    dp = 0.0
    dq = 0.0
    for a in range(3):
        e = dst[i, a] - dst[j, a]
        f = src[i, a] - src[j, a]
        dp += e * e
        dq += f * f
    return abs(np.sqrt(dp) - np.sqrt(dq)) <= thr


@njit(cache=True, parallel=True)
def consistency_degrees(src, dst, seeds, thr):
    """For each seed, how many other correspondences are length-consistent with it. O(M N) time, O(M) memory."""
    n = src.shape[0]
    deg = np.zeros(seeds.shape[0], dtype=np.int64)
    for k in prange(seeds.shape[0]):
        i = seeds[k]
        c = 0
        for j in range(n):
            if j != i and _consistent(src, dst, i, j, thr):
                c += 1
        deg[k] = c
    return deg


@njit(cache=True)
def seed_clique(src, dst, seed, thr, max_set):
    """A large clique of mutually consistent correspondences containing `seed`.

    The seed's consistent set (strided down to `max_set` members) is peeled: the member with the
    fewest consistent partners inside the set goes first, until every remaining pair is consistent.
    Memory: O(N + max_set^2).
    """
    n = src.shape[0]
    members = np.empty(n, dtype=np.int64)
    m = 0
    for j in range(n):
        if j != seed and _consistent(src, dst, seed, j, thr):
            members[m] = j
            m += 1
    stride = 1 + (m - 1) // (max_set - 1) if m > max_set - 1 else 1
    sel = np.empty(max_set, dtype=np.int64)
    sel[0] = seed
    s = 1
    for k in range(0, m, stride):
        if s >= max_set:
            break
        sel[s] = members[k]
        s += 1
    adj = np.zeros((s, s), dtype=np.bool_)
    deg = np.zeros(s, dtype=np.int64)
    for a in range(s):
        for b in range(a + 1, s):
            if a == 0 or _consistent(src, dst, sel[a], sel[b], thr):
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


@njit(cache=True, parallel=True)
def clique_hypotheses(src, dst, seeds, thr, max_set, inlier_bound):
    """One rigid hypothesis per seed: the Kabsch fit of its clique, scored by how many of all
    correspondences it brings within `inlier_bound`. Returns (Rs, ts, scores, clique_sizes)."""
    m = seeds.shape[0]
    n = src.shape[0]
    Rs = np.zeros((m, 3, 3))
    ts = np.zeros((m, 3))
    scores = np.zeros(m, dtype=np.int64)
    sizes = np.zeros(m, dtype=np.int64)
    all_idx = np.arange(n)
    bound2 = inlier_bound * inlier_bound
    for k in prange(m):
        clique = seed_clique(src, dst, seeds[k], thr, max_set)
        sizes[k] = clique.shape[0]
        if clique.shape[0] < 3:
            continue
        R, t, ok = weighted_kabsch(src, dst, clique, np.ones(clique.shape[0]))
        if not ok:
            continue
        Rs[k] = R
        ts[k] = t
        r2 = squared_residuals(src, dst, all_idx, R, t)
        scores[k] = np.sum(r2 <= bound2)
    return Rs, ts, scores, sizes


@njit(cache=True)
def rescoring_losses(src, dst, Rs, ts, alpha):
    """Geman-McClure loss at scale alpha of each candidate transform over all correspondences."""
    all_idx = np.arange(src.shape[0])
    out = np.empty(Rs.shape[0])
    for k in range(Rs.shape[0]):
        out[k] = gm_loss(squared_residuals(src, dst, all_idx, Rs[k], ts[k]), alpha)
    return out
