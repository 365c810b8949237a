"""Splitting the correspondences into sub-sets (SANDRO's splitting strategy)."""

from __future__ import annotations

import numpy as np
from numba import njit

from sandro_core.config import SplitStrategy


@njit(cache=True)
def _splitmix64(x):
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True)
def _coordinate_hash(bits, seed):
    out = np.empty(bits.shape[0], dtype=np.uint64)
    for i in range(bits.shape[0]):
        h = _splitmix64(np.uint64(seed))
        for c in range(bits.shape[1]):
            h = _splitmix64(h ^ bits[i, c])
        out[i] = h
    return out


def correspondence_order(source: np.ndarray, target: np.ndarray, seed: int) -> np.ndarray:
    """A seeded pseudo-random order of the correspondences that depends only on their coordinates.

    Hashing the coordinates (instead of drawing a permutation) makes every seeded choice the
    solver makes invariant to the order in which the correspondences are given.
    """
    bits = np.ascontiguousarray(np.hstack([source, target]), dtype=np.float64).view(np.uint64)
    return np.argsort(_coordinate_hash(bits, seed % 2**64), kind="stable")


def split_indices(
    source: np.ndarray,
    target: np.ndarray,
    candidates: np.ndarray,
    num_splits: int,
    strategy: SplitStrategy,
    seed: int,
) -> list[np.ndarray]:
    """Cut `candidates` (indices into source/target) into `num_splits` sub-sets of equal size.

    contiguous: in the given order (the paper); random: seeded, by coordinate hash; spatial: slabs
    along the principal axis of the source points.
    """
    if strategy == "contiguous":
        order = candidates
    elif strategy == "random":
        order = candidates[correspondence_order(source[candidates], target[candidates], seed)]
    elif strategy == "spatial":
        pts = source[candidates]
        centred = pts - pts.mean(axis=0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        order = candidates[np.argsort(centred @ axis, kind="stable")]
    else:
        raise ValueError(f"unknown split strategy {strategy!r}")
    return [np.ascontiguousarray(part) for part in np.array_split(order, num_splits)]
