"""Place recognition across sessions: a yaw-invariant ring descriptor per keyframe submap."""

from __future__ import annotations

import numpy as np

from sandro_slam.candidates import ring_key
from sandro_slam.config import SlamConfig
from sandro_slam.merge.loops import Descriptions
from sandro_slam.session import Session


def place_candidates(
    sessions: list[Session], descriptions: Descriptions, config: SlamConfig
) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """Per pair of sessions (i < j): keyframe pairs (key in i, key in j) with the most similar ring keys, at
    most `candidates_per_keyframe` per keyframe of j, most similar first."""
    keys = [list(d) for d in descriptions]
    rings = [
        np.array([ring_key(s.submaps[k], config.merge.descriptor_radius) for k in ks]).reshape(len(ks), -1)
        for s, ks in zip(sessions, keys)
    ]
    found = {}
    for j in range(len(sessions)):
        for i in range(j):
            if not keys[i] or not keys[j]:
                continue
            distance = np.linalg.norm(rings[j][:, None, :] - rings[i][None, :, :], axis=2)
            best = np.argsort(distance, axis=1)[:, : config.merge.candidates_per_keyframe]
            pairs = sorted((distance[b, a], keys[i][a], keys[j][b]) for b in range(len(best)) for a in best[b])
            found[(i, j)] = [(ki, kj) for _, ki, kj in pairs]
    return found
