"""Voting on the transform between two sessions: the verified loops that agree on one."""

from __future__ import annotations

import numpy as np

from sandro_core.geometry import rotation_angle
from sandro_slam.config import MergeConfig
from sandro_slam.merge.loops import InterSessionLoop
from sandro_slam.session import Session


def implied(sessions: list[Session], loop: InterSessionLoop) -> np.ndarray:
    """T_i_j (session j's world into session i's) that a loop implies, from the sessions' own poses."""
    T_i = sessions[loop.target_session].keyframe_poses[loop.target_key]
    T_j = sessions[loop.source_session].keyframe_poses[loop.source_key]
    return T_i @ loop.T_target_source @ np.linalg.inv(T_j)


def agree(sessions: list[Session], a: InterSessionLoop, b: InterSessionLoop, merge: MergeConfig) -> bool:
    """Whether two loops between the same sessions imply the same session transform: they move both source
    keyframes' positions to within `consistency_translation` and differ by `consistency_rotation_deg`."""
    source = sessions[a.source_session].keyframe_poses
    return _alike(implied(sessions, a), implied(sessions, b), [source[a.source_key], source[b.source_key]], merge)


def fits(sessions: list[Session], loop: InterSessionLoop, T_i_j: np.ndarray, merge: MergeConfig) -> bool:
    """Whether a loop agrees, where it is, with the session transform T_i_j (the `agree` tolerances)."""
    source = sessions[loop.source_session].keyframe_poses[loop.source_key]
    return _alike(implied(sessions, loop), T_i_j, [source], merge)


def _alike(T_a: np.ndarray, T_b: np.ndarray, poses: list[np.ndarray], merge: MergeConfig) -> bool:
    """Whether two session transforms differ by at most `consistency_rotation_deg` and move the positions of
    `poses` (4x4) to within `consistency_translation` of each other."""
    if np.degrees(rotation_angle(T_a[:3, :3].T @ T_b[:3, :3])) > merge.consistency_rotation_deg:
        return False
    return all(
        np.linalg.norm((T_a @ pose[:, 3] - T_b @ pose[:, 3])[:3]) <= merge.consistency_translation for pose in poses
    )


def vote(
    sessions: list[Session], loops: list[InterSessionLoop], merge: MergeConfig
) -> tuple[InterSessionLoop | None, list[InterSessionLoop]]:
    """The loop whose agreeing loops (itself included) hold the most SANDRO inliers, and those loops.

    Counting inliers rather than loops matters in repetitive places: aliased matches (a street that looks
    like the next one) can agree with each other as often as the true ones do, but with fewer inliers."""
    best, best_set, best_score = None, [], 0
    for loop in loops:
        voters = [other for other in loops if other is loop or agree(sessions, loop, other, merge)]
        score = sum(other.inliers for other in voters)
        if score > best_score:
            best, best_set, best_score = loop, voters, score
    return best, best_set


def spanning_transforms(
    sessions: list[Session], joined: dict[tuple[int, int], InterSessionLoop | None], reachable_only: bool = False
) -> dict[int, np.ndarray]:
    """T_merged_session for every session reachable from the first through joined pairs (breadth first);
    with `reachable_only` the transforms are placeholders (identity)."""
    T = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        i = frontier.pop(0)
        for (a, b), best in joined.items():
            if i not in (a, b) or (a in T and b in T):
                continue
            other = b if a == i else a
            if reachable_only:
                T[other] = np.eye(4)
            else:
                T_a_b = implied(sessions, best)
                T[other] = T[i] @ (T_a_b if a == i else np.linalg.inv(T_a_b))
            frontier.append(other)
    return T
