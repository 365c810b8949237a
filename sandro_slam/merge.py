"""Joining sessions recorded at different times into one map, with no initial alignment.

1. Place recognition (yaw-invariant ring keys of the submaps) proposes keyframe pairs across sessions.
2. Each pair is registered with the loop-closure registration (FPFH, SANDRO, ICP, verification).
3. Per pair of sessions, the verified loops vote on the session-to-session transform; the pair is joined
   only when at least `min_loops` of them agree, and when the voted alignment passes the free-space test.
   Free-space test (the guard against aliasing: a street that looks like another one, 280 m away, lets
   many loops agree on the wrong shift): each of the agreeing loops, most inliers first, puts one submap's
   keypoints into the other's frame; the share of them lying where the other session's rays passed freely
   (voxels its rays crossed, away from any of its points and above its ground) is that loop's conflict.
   A static world seen twice gives almost none; an aliased place differs in its small things (trees,
   poles, parked cars, a missing or taller building), which land in the other session's free street.
   Single loops overlap (simulated: true up to 0.035, aliased from 0.04), so the pair is judged by the
   median conflict over its agreeing loops, refused above `max_free_space_conflict` (0.03). Medians measured
   by sandro-bench merge: 0.002-0.003 on true overlaps (0.0125 on the single-sweep sessions of the tests),
   0.075-0.103 on 20 aliased pairs.
4. Once aligned, keyframe pairs that now lie close together are registered too (guided search).
5. One gtsam graph: every session's odometry and accepted loop factors (keys gtsam.symbol('a' + session
   index, key)), the inter-session loops, a prior on the first session's first keyframe; the robust back end
   with everything but the inter-session loops as known inliers. Pairs whose loops the back end rejects
   are split again; sessions left unconnected to the first are refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from sandro_slam.config import MergeConfig, SlamConfig
from sandro_slam.keyframes import rotation_angle
from sandro_slam.loop_registration import SubmapDescription, describe_submap, register_submaps
from sandro_slam.pose_graph import between_factor, robust_optimize
from sandro_slam.session import Session

MIN_SUBMAP_POINTS = 10


@dataclass
class InterSessionLoop:
    """A verified loop between keyframes of two sessions: T_target_source maps the source keyframe's
    points into the target keyframe's frame."""

    target_session: int  # index into the sessions given
    target_key: int
    source_session: int
    source_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam order [rotation, translation], right perturbation
    inliers: int
    overlap: float
    found_by: str  # "place_recognition" or "guided"
    voted: bool = False  # agrees with the session transform its pair of sessions voted for (only these are used)
    conflict: float = float("nan")  # free-space conflict (see the module docstring); nan: not tested
    weight: float = float("nan")  # robust back end's weight (below 0.5: rejected; nan: not in the graph)


@dataclass
class MergeResult:
    """The merged frame is the first session's world frame.

    T_merged_session[name]: 4x4 mapping the session's world frame into the merged frame. covariance[name]:
    6x6 marginal covariance of the session's first keyframe pose in the merged graph, gtsam Pose3 order
    [rotation, translation], right perturbation (in that keyframe's frame); the first session's reflects
    the prior only. keyframe_poses / frame_poses: T_merged_keyframe / T_merged_frame per joined session.
    """

    names: list[str]
    joined: list[str]
    refused: dict[str, str]  # session name -> why it could not be joined
    T_merged_session: dict[str, np.ndarray]
    covariance: dict[str, np.ndarray]
    keyframe_poses: dict[str, dict[int, np.ndarray]]
    frame_poses: dict[str, np.ndarray]
    loops: list[InterSessionLoop]  # all verified inter-session loops, with their weights
    graph: gtsam.NonlinearFactorGraph  # the merged graph (keys: session_key)
    values: gtsam.Values  # its optimised values
    timings: dict[str, float] = field(default_factory=dict)  # seconds

    @property
    def ok(self) -> bool:
        """True when every session was joined."""
        return not self.refused


def session_key(session_index: int, key: int) -> int:
    """The merged graph's key of keyframe `key` of session `session_index`."""
    return gtsam.symbol(chr(ord("a") + session_index), key)


def merge_sessions(sessions: list[Session], config: SlamConfig | None = None) -> MergeResult:
    """Join `sessions` (each in its own world frame) into the first one's frame; see the module docstring."""
    config = config or SlamConfig()
    merge = config.merge
    _check(sessions)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    descriptions = [{k: describe_submap(s.submaps[k], config.registration) for k in s.keys
                     if len(s.submaps[k]) >= MIN_SUBMAP_POINTS} for s in sessions]
    timings["describe"] = time.perf_counter() - start

    tic = time.perf_counter()
    candidates = _place_recognition(sessions, descriptions, config)
    timings["place_recognition"] = time.perf_counter() - tic

    tic = time.perf_counter()
    loops: list[InterSessionLoop] = []
    tried: set[tuple[int, int, int, int]] = set()
    for (i, j), pairs in candidates.items():
        for ki, kj in pairs[: merge.max_candidate_pairs]:
            loop = _register(i, ki, j, kj, descriptions, config, "place_recognition")
            tried.add((i, ki, j, kj))
            if loop is not None:
                loops.append(loop)
    votes = {(i, j): _agreeing(sessions, [lp for lp in loops if (lp.target_session, lp.source_session) == (i, j)],
                               merge) for i in range(len(sessions)) for j in range(i + 1, len(sessions))}
    timings["registration"] = time.perf_counter() - tic

    tic = time.perf_counter()
    free = _FreeSpace(descriptions, merge.free_space_voxel)
    conflicts = {pair: _pair_conflict(agreeing, descriptions, free, merge)
                 for pair, (_, agreeing) in votes.items() if len(agreeing) >= merge.min_loops}
    timings["free_space_test"] = time.perf_counter() - tic

    refused: dict[str, str] = {}
    joined_pairs = {pair: votes[pair][0] for pair, conflict in conflicts.items()
                    if conflict <= merge.max_free_space_conflict}
    for loop in loops:  # loops disagreeing with the vote of their pair stay out of the graph
        loop.voted = any(loop in votes[pair][1] for pair in joined_pairs)
    T_merged = _spanning_transforms(sessions, joined_pairs, loops)
    for index, session in enumerate(sessions):
        if index not in T_merged:
            refused[session.name] = _why(index, votes, conflicts, loops, merge)

    tic = time.perf_counter()
    if merge.guided_radius > 0 and len(T_merged) > 1:
        loops += _guided_loops(sessions, T_merged, descriptions, tried, config)
    timings["guided_registration"] = time.perf_counter() - tic

    tic = time.perf_counter()
    while True:
        graph, values, known, loop_factors = _build_graph(sessions, T_merged, loops, config.graph.prior_sigma)
        estimate, weights = robust_optimize(graph, values, known, config.graph) if loop_factors \
            else (gtsam.LevenbergMarquardtOptimizer(graph, values).optimize(), np.ones(graph.size()))
        for loop in loops:
            loop.weight = float("nan")
        for loop, index in loop_factors:
            loop.weight = float(weights[index])
        accepted = _accepted_pairs(loops, merge.min_loops)
        kept = _spanning_transforms(sessions, {pair: None for pair in accepted}, [], reachable_only=True)
        dropped = [index for index in T_merged if index not in kept]
        if not dropped:
            break
        for index in dropped:
            n = sum(1 for lp in loops if index in (lp.target_session, lp.source_session) and lp.weight >= 0.5)
            refused[sessions[index].name] = (f"the robust back end kept only {n} of its inter-session loops "
                                             f"(at least {merge.min_loops} needed with a joined session)")
            del T_merged[index]
    timings["optimization"] = time.perf_counter() - tic

    tic = time.perf_counter()
    result = _result(sessions, T_merged, refused, loops, graph, estimate, known, loop_factors)
    timings["marginals"] = time.perf_counter() - tic
    timings["total"] = time.perf_counter() - start
    result.timings = timings
    return result


def _check(sessions: list[Session]) -> None:
    if len(sessions) < 2:
        raise ValueError(f"merging needs at least two sessions, got {len(sessions)}")
    if len(sessions) > 26:
        raise ValueError(f"at most 26 sessions can be merged, got {len(sessions)}")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ValueError(f"session names must differ: {names}")
    for session in sessions:
        session.check()


def ring_key(points: np.ndarray, radius: float, rings: int = 10, sectors: int = 60,
             heights: tuple[float, ...] = (-1.0, 1.0, 4.0, 10.0)) -> np.ndarray:
    """A yaw-invariant place descriptor of a submap (points in the keyframe frame, z up [m]): per height band
    (edges `heights` above the keyframe origin) and ring (up to `radius`), the share of azimuth sectors
    holding a point."""
    r = np.linalg.norm(points[:, :2], axis=1)
    inside = r < radius
    ring = (r[inside] / radius * rings).astype(int)
    sector = ((np.arctan2(points[inside, 1], points[inside, 0]) + np.pi) / (2 * np.pi) * sectors).astype(int)
    band = np.digitize(points[inside, 2], heights)
    occupied = np.zeros((len(heights) + 1, rings, sectors))
    occupied[band, ring, sector % sectors] = 1.0
    return occupied.mean(axis=2).ravel()


def _place_recognition(sessions: list[Session], descriptions: list[dict[int, SubmapDescription]],
                       config: SlamConfig) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """Per pair of sessions (i < j): keyframe pairs (key in i, key in j) with the most similar ring keys, at
    most `candidates_per_keyframe` per keyframe of j, most similar first."""
    keys = [list(d) for d in descriptions]
    rings = [np.array([ring_key(s.submaps[k], config.merge.descriptor_radius) for k in ks]).reshape(len(ks), -1)
             for s, ks in zip(sessions, keys)]
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


def _register(i: int, ki: int, j: int, kj: int, descriptions: list[dict[int, SubmapDescription]],
              config: SlamConfig, found_by: str) -> InterSessionLoop | None:
    pair = register_submaps(descriptions[i][ki], descriptions[j][kj], config.registration)
    if not pair.accepted:
        return None
    return InterSessionLoop(i, ki, j, kj, pair.T_target_source, pair.covariance, pair.inliers, pair.overlap,
                            found_by)


def _implied(sessions: list[Session], loop: InterSessionLoop) -> np.ndarray:
    """T_i_j (session j's world into session i's) that a loop implies, from the sessions' own poses."""
    T_i = sessions[loop.target_session].keyframe_poses[loop.target_key]
    T_j = sessions[loop.source_session].keyframe_poses[loop.source_key]
    return T_i @ loop.T_target_source @ np.linalg.inv(T_j)


def _agree(sessions: list[Session], a: InterSessionLoop, b: InterSessionLoop, merge: MergeConfig) -> bool:
    """Whether two loops between the same sessions imply the same session transform: they move both source
    keyframes' positions to within `consistency_translation` and differ by `consistency_rotation_deg`."""
    source = sessions[a.source_session].keyframe_poses
    return _alike(_implied(sessions, a), _implied(sessions, b), [source[a.source_key], source[b.source_key]], merge)


def _fits(sessions: list[Session], loop: InterSessionLoop, T_i_j: np.ndarray, merge: MergeConfig) -> bool:
    """Whether a loop agrees, where it is, with the session transform T_i_j (the `_agree` tolerances)."""
    source = sessions[loop.source_session].keyframe_poses[loop.source_key]
    return _alike(_implied(sessions, loop), T_i_j, [source], merge)


def _alike(T_a: np.ndarray, T_b: np.ndarray, poses: list[np.ndarray], merge: MergeConfig) -> bool:
    """Whether two session transforms differ by at most `consistency_rotation_deg` and move the positions of
    `poses` (4x4) to within `consistency_translation` of each other."""
    if np.degrees(rotation_angle(T_a[:3, :3].T @ T_b[:3, :3])) > merge.consistency_rotation_deg:
        return False
    return all(np.linalg.norm((T_a @ pose[:, 3] - T_b @ pose[:, 3])[:3]) <= merge.consistency_translation
               for pose in poses)


def _agreeing(sessions: list[Session], loops: list[InterSessionLoop],
              merge: MergeConfig) -> tuple[InterSessionLoop | None, list[InterSessionLoop]]:
    """The loop whose agreeing loops (itself included) hold the most SANDRO inliers, and those loops.

    Counting inliers rather than loops matters in repetitive places: aliased matches (a street that looks
    like the next one) can agree with each other as often as the true ones do, but with fewer inliers."""
    best, best_set, best_score = None, [], 0
    for loop in loops:
        agreeing = [other for other in loops if other is loop or _agree(sessions, loop, other, merge)]
        score = sum(other.inliers for other in agreeing)
        if score > best_score:
            best, best_set, best_score = loop, agreeing, score
    return best, best_set


class _FreeSpace:
    """Per keyframe (session index, key), computed on first use: the voxels its keypoints' rays crossed
    freely, and its ground plane."""

    def __init__(self, descriptions: list[dict[int, SubmapDescription]], voxel: float):
        self.descriptions, self.voxel = descriptions, voxel
        self._cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}

    def get(self, session: int, key: int) -> tuple[np.ndarray, np.ndarray | None]:
        if (session, key) not in self._cache:
            cloud = self.descriptions[session][key].cloud
            self._cache[(session, key)] = free_voxels(np.asarray(cloud.points), np.asarray(cloud.normals),
                                                      self.voxel)
        return self._cache[(session, key)]


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 per voxel of edge `voxel` [m] (21 bits per axis: +-1e6 voxels)."""
    index = np.floor(points / voxel).astype(np.int64) + (1 << 20)
    return (index[:, 0] << 42) | (index[:, 1] << 21) | index[:, 2]


def ground_plane(points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
    """(a, b, c) of the ground z = a x + b y + c [m] in a keyframe frame (z up, the sensor above the ground),
    fitted to points at least 0.5 m below the sensor with upright normals; None when there are too few."""
    candidates = points[(np.abs(normals[:, 2]) > 0.9) & (points[:, 2] < -0.5)]
    if len(candidates) < 10:
        return None
    A = np.c_[candidates[:, :2], np.ones(len(candidates))]
    plane = np.linalg.lstsq(A, candidates[:, 2], rcond=None)[0]
    for _ in range(2):
        near = np.abs(A @ plane - candidates[:, 2]) < 0.3
        if near.sum() < 3:
            break
        plane = np.linalg.lstsq(A[near], candidates[near, 2], rcond=None)[0]
    return plane


def _above(points: np.ndarray, plane: np.ndarray | None, height: float) -> np.ndarray:
    """Mask of points more than `height` [m] above the ground plane (all, without a plane)."""
    if plane is None:
        return np.ones(len(points), dtype=bool)
    return points[:, 2] - (points[:, :2] @ plane[:2] + plane[2]) > height


def free_voxels(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Voxels (sorted `_voxel_keys`) that rays from the keyframe origin to its points (keyframe frame [m])
    crossed without a return, and the ground plane.

    A ray counts up to `voxel` short of its surface, measured normal to that surface (a grazing ray stops
    early), and only more than `voxel` above the ground; voxels next to any point are never free."""
    distance = np.linalg.norm(points, axis=1)
    keep = distance > voxel
    points, normals, distance = points[keep], normals[keep], distance[keep]
    direction = points / distance[:, None]
    incidence = np.abs(np.sum(direction * normals, axis=1))
    step = 0.5 * voxel
    steps = np.maximum(0, ((distance - voxel / np.maximum(incidence, 0.05)) / step).astype(np.int64))
    ray = np.repeat(np.arange(len(points)), steps)
    along = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps) + 1) * step
    samples = direction[ray] * along[:, None]
    plane = ground_plane(points, normals)
    free = np.unique(_voxel_keys(samples[_above(samples, plane, voxel)], voxel))
    around = voxel * np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    occupied = np.unique(_voxel_keys((points[:, None, :] + around[None]).reshape(-1, 3), voxel))
    return np.setdiff1d(free, occupied, assume_unique=True), plane


def free_space_conflict(free: np.ndarray, plane: np.ndarray | None, points: np.ndarray, T_target_source: np.ndarray,
                        voxel: float) -> tuple[int, int]:
    """(conflicting, tested): of the source `points` more than `voxel` above the target's ground once moved
    by T_target_source, how many lie in the target's `free` voxels (from `free_voxels`)."""
    moved = points @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    keys = _voxel_keys(moved[_above(moved, plane, voxel)], voxel)
    at = np.minimum(np.searchsorted(free, keys), max(len(free) - 1, 0))
    hits = int(np.sum(free[at] == keys)) if len(free) else 0
    return hits, len(keys)


def _loop_conflict(loop: InterSessionLoop, descriptions: list[dict[int, SubmapDescription]], free: _FreeSpace,
                   voxel: float) -> float:
    """The loop's conflict: the share of both submaps' keypoints in the other's free space."""
    hits, tested = 0, 0
    for (i, ki), (j, kj), T in (((loop.target_session, loop.target_key), (loop.source_session, loop.source_key),
                                 loop.T_target_source),
                                ((loop.source_session, loop.source_key), (loop.target_session, loop.target_key),
                                 np.linalg.inv(loop.T_target_source))):
        h, n = free_space_conflict(*free.get(i, ki), descriptions[j][kj].keypoints, T, voxel)
        hits, tested = hits + h, tested + n
    return hits / tested if tested else 0.0


def _pair_conflict(agreeing: list[InterSessionLoop], descriptions: list[dict[int, SubmapDescription]],
                   free: _FreeSpace, merge: MergeConfig) -> float:
    """Median conflict of the `conflict_loops` agreeing loops with the most inliers (stored on the loops)."""
    tested = sorted(agreeing, key=lambda lp: -lp.inliers)[: merge.conflict_loops]
    for loop in tested:
        loop.conflict = _loop_conflict(loop, descriptions, free, merge.free_space_voxel)
    return float(np.median([loop.conflict for loop in tested]))


def _spanning_transforms(sessions: list[Session], joined: dict[tuple[int, int], InterSessionLoop | None],
                         loops: list[InterSessionLoop], reachable_only: bool = False) -> dict[int, np.ndarray]:
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
                T_a_b = _implied(sessions, best)
                T[other] = T[i] @ (T_a_b if a == i else np.linalg.inv(T_a_b))
            frontier.append(other)
    return T


def _why(index: int, votes: dict, conflicts: dict[tuple[int, int], float], loops: list[InterSessionLoop],
         merge: MergeConfig) -> str:
    """Why session `index` could not be joined by the votes of its verified loops."""
    mine = [lp for lp in loops if index in (lp.target_session, lp.source_session)]
    if not mine:
        return "no inter-session loop passed verification (the sessions do not seem to overlap)"
    tested = {pair: c for pair, c in conflicts.items() if index in pair}
    if tested:
        pair = min(tested, key=tested.get)
        return (f"{len(votes[pair][1])} inter-session loops agree on one transform, but it puts a median "
                f"{100 * tested[pair]:.1f} % of the submap keypoints where the other session saw free space "
                f"(at most {100 * merge.max_free_space_conflict:.1f} %): an aliased place, not an overlap")
    agree = max(len(agreeing) for pair, (_, agreeing) in votes.items() if index in pair)
    return (f"{len(mine)} inter-session loops passed verification but at most {agree} agree on one transform "
            f"(at least {merge.min_loops} needed)")


def _guided_loops(sessions: list[Session], T_merged: dict[int, np.ndarray],
                  descriptions: list[dict[int, SubmapDescription]], tried: set[tuple[int, int, int, int]],
                  config: SlamConfig) -> list[InterSessionLoop]:
    """Register, for every keyframe of a joined session, the nearest keyframe of each earlier joined session
    within `guided_radius` in the merged frame (pairs not tried yet)."""
    found = []
    joined = sorted(T_merged)
    positions = {i: (np.array([T_merged[i] @ sessions[i].keyframe_poses[k][:, 3] for k in descriptions[i]])[:, :3],
                     list(descriptions[i])) for i in joined if descriptions[i]}
    for a, j in enumerate(joined):
        for kj in descriptions[j]:
            p = (T_merged[j] @ sessions[j].keyframe_poses[kj][:, 3])[:3]
            for i in joined[:a]:
                if i not in positions:
                    continue
                xyz, keys = positions[i]
                distance = np.linalg.norm(xyz - p, axis=1)
                nearest = int(np.argmin(distance))
                ki = keys[nearest]
                if distance[nearest] > config.merge.guided_radius or (i, ki, j, kj) in tried:
                    continue
                tried.add((i, ki, j, kj))
                loop = _register(i, ki, j, kj, descriptions, config, "guided")
                if loop is not None:
                    loop.voted = _fits(sessions, loop, np.linalg.inv(T_merged[i]) @ T_merged[j], config.merge)
                    found.append(loop)
    return found


def _build_graph(sessions: list[Session], T_merged: dict[int, np.ndarray], loops: list[InterSessionLoop],
                 prior_sigma: float):
    """The merged graph over the joined sessions: (graph, initial values, known inlier factor indices,
    [(loop, factor index)] of the inter-session loops)."""
    graph, values, known = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    prior = gtsam.noiseModel.Isotropic.Sigma(6, prior_sigma)
    for index in sorted(T_merged):
        session = sessions[index]
        for key in session.keys:
            values.insert(session_key(index, key), gtsam.Pose3(T_merged[index] @ session.keyframe_poses[key]))
        if index == 0:
            first = session_key(0, session.keys[0])
            known.append(graph.size())
            graph.add(gtsam.PriorFactorPose3(first, values.atPose3(first), prior))
        for edge in session.edges:
            if edge.accepted:
                known.append(graph.size())
                graph.add(edge.factor(session_key(index, edge.target), session_key(index, edge.source)))
    loop_factors = []
    for loop in loops:
        if loop.voted and loop.target_session in T_merged and loop.source_session in T_merged:
            loop_factors.append((loop, graph.size()))
            graph.add(between_factor(session_key(loop.target_session, loop.target_key),
                                     session_key(loop.source_session, loop.source_key),
                                     loop.T_target_source, loop.covariance))
    return graph, values, known, loop_factors


def _accepted_pairs(loops: list[InterSessionLoop], min_loops: int) -> list[tuple[int, int]]:
    """Session pairs joined by at least `min_loops` inter-session loops the back end kept."""
    counts: dict[tuple[int, int], int] = {}
    for loop in loops:
        if loop.weight >= 0.5:
            pair = (loop.target_session, loop.source_session)
            counts[pair] = counts.get(pair, 0) + 1
    return [pair for pair, n in counts.items() if n >= min_loops]


def _result(sessions: list[Session], T_merged: dict[int, np.ndarray], refused: dict[str, str],
            loops: list[InterSessionLoop], graph: gtsam.NonlinearFactorGraph, estimate: gtsam.Values,
            known: list[int], loop_factors: list[tuple[InterSessionLoop, int]]) -> MergeResult:
    """Poses, session transforms and their marginal covariances (on the graph without rejected loops)."""
    kept = gtsam.NonlinearFactorGraph()
    for index in known + [index for loop, index in loop_factors if loop.weight >= 0.5]:
        kept.add(graph.at(index))
    marginals = gtsam.Marginals(kept, estimate)
    names = [s.name for s in sessions]
    result = MergeResult(names, [], refused, {}, {}, {}, {}, loops, graph, estimate)
    for index in sorted(T_merged):
        session = sessions[index]
        poses = {k: estimate.atPose3(session_key(index, k)).matrix() for k in session.keys}
        first = session.keys[0]
        result.joined.append(session.name)
        result.T_merged_session[session.name] = poses[first] @ np.linalg.inv(session.keyframe_poses[first])
        result.covariance[session.name] = np.asarray(marginals.marginalCovariance(session_key(index, first)))
        result.keyframe_poses[session.name] = poses
        result.frame_poses[session.name] = session.frame_poses(poses)
    return result
