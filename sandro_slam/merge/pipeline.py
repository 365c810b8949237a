"""merge_sessions: the steps of a merge in order (see the package docstring)."""

from __future__ import annotations

import time
from collections.abc import Callable

import gtsam
import numpy as np

from sandro_slam.config import MergeConfig, SlamConfig
from sandro_slam.loop_registration import MIN_SUBMAP_POINTS, describe_submap
from sandro_slam.merge.descriptor import place_candidates
from sandro_slam.merge.free_space import FreeSpace, pair_conflict
from sandro_slam.merge.graph import MergeResult, accepted_pairs, build_graph, group_name, merge_result
from sandro_slam.merge.loops import Descriptions, InterSessionLoop, register_pairs
from sandro_slam.merge.voting import fits, spanning_transforms, vote
from sandro_slam.robust_backend import refined, robust_optimize
from sandro_slam.session import Session
from sandro_slam.timing import Stopwatch
from sandro_slam.variance_components import reweighted

MapFunction = Callable[[Callable, list[tuple]], list]  # (function, argument tuples) -> results, in order


def serial_map(function: Callable, arguments: list[tuple]) -> list:
    """`function(*args)` for every tuple of `arguments`, one after the other in this process."""
    return [function(*args) for args in arguments]


def merge_config(config: SlamConfig, sessions: list[Session]) -> SlamConfig:
    """`config` with its lengths resolved (`SlamConfig.resolved`) at `config.scale`, else at the median scale the
    sessions were mapped at (1 when none is known)."""
    known = [s.scale for s in sessions if s.scale is not None]
    return config.resolved(config.scale if config.scale is not None or not known else float(np.median(known)))


def merge_sessions(
    sessions: list[Session], config: SlamConfig | None = None, map_function: MapFunction = serial_map
) -> MergeResult:
    """Join `sessions` (each in its own world frame) into the first one's frame; see the package docstring.

    `map_function` runs the independent expensive steps, the submap descriptions and the pair registrations: serial
    by default, or spread over workers (`pipelines.cluster.ray_map`); the result does not depend on it. Lengths
    the configuration leaves None: see `merge_config`."""
    config = merge_config(config or SlamConfig(), sessions)
    merge = config.merge
    _check(sessions)
    start = time.perf_counter()
    stopwatch = Stopwatch()
    with stopwatch("describe"):
        keys = [[k for k in s.keys if len(s.submaps[k]) >= MIN_SUBMAP_POINTS] for s in sessions]
        described = iter(
            map_function(
                describe_submap, [(s.submaps[k], config.registration) for s, ks in zip(sessions, keys) for k in ks]
            )
        )
        descriptions = [{k: next(described) for k in ks} for ks in keys]
    with stopwatch("place_recognition"):
        candidates = place_candidates(sessions, descriptions, config)
    with stopwatch("registration"):
        pairs = [
            (i, ki, j, kj) for (i, j), chosen in candidates.items() for ki, kj in chosen[: merge.max_candidate_pairs]
        ]
        loops = register_pairs(pairs, descriptions, config, "place_recognition", map_function)
        tried = set(pairs)
        votes = {
            (i, j): vote(sessions, [lp for lp in loops if (lp.target_session, lp.source_session) == (i, j)], merge)
            for i in range(len(sessions))
            for j in range(i + 1, len(sessions))
        }
    with stopwatch("free_space_test"):
        free = FreeSpace(descriptions, merge.free_space_voxel)
        conflicts = {
            pair: pair_conflict(voters, descriptions, free, merge)
            for pair, (_, voters) in votes.items()
            if len(voters) >= merge.min_loops
        }

    joined_pairs = {
        pair: votes[pair][0] for pair, conflict in conflicts.items() if conflict <= merge.max_free_space_conflict
    }
    for loop in loops:  # loops disagreeing with the vote of their pair stay out of the graph
        loop.voted = any(loop in votes[pair][1] for pair in joined_pairs)
    T_merged = spanning_transforms(sessions, joined_pairs)
    refused = {
        session.name: _why(index, votes, conflicts, loops, merge)
        for index, session in enumerate(sessions)
        if index not in T_merged
    }

    with stopwatch("guided_registration"):
        if merge.guided_radius > 0 and len(T_merged) > 1:
            loops += _guided_loops(sessions, T_merged, descriptions, tried, config, map_function)
    with stopwatch("optimization"):
        graph, estimate, known, loop_factors, factors = _optimize(sessions, T_merged, loops, refused, config)
    with stopwatch("marginals"):
        result = merge_result(sessions, T_merged, refused, loops, graph, estimate, known, loop_factors)
    result.timings = {**stopwatch.seconds, "total": time.perf_counter() - start}
    result.variance_factors = {group_name(group, sessions): factor for group, factor in factors.items()}
    return result


def _optimize(
    sessions: list[Session],
    T_merged: dict[int, np.ndarray],
    loops: list[InterSessionLoop],
    refused: dict[str, str],
    config: SlamConfig,
):
    """Optimise the merged graph with the robust back end (setting each loop's weight); a session whose
    inter-session loops the back end rejects until it is no longer joined to the first is refused (taken out of
    `T_merged`, its reason added to `refused`) and the graph optimised again. Returns `build_graph`'s graph (with
    `graph.loop_submap_noise`: its loops widened, as the estimate weighs them once they are decided; with
    `merge.variance_components` each group of factors scaled by its variance factor), known inliers and loop
    factors, with the optimised values, and the variance factor of each group (empty without)."""
    min_loops = config.merge.min_loops
    while True:
        graph, values, known, loop_factors, groups = build_graph(sessions, T_merged, loops, config.graph.prior_sigma)
        estimate, weights = (
            robust_optimize(graph, values, known, config.graph)
            if loop_factors
            else (gtsam.LevenbergMarquardtOptimizer(graph, values).optimize(), np.ones(graph.size()))
        )
        if config.graph.loop_submap_noise:  # loops decided: the estimate weighs them as `PoseGraph` does
            graph = build_graph(sessions, T_merged, loops, config.graph.prior_sigma, loop_submap_noise=True)[0]
            estimate = refined(graph, estimate, weights)
        for loop in loops:
            loop.weight = float("nan")
        for loop, index in loop_factors:
            loop.weight = float(weights[index])
        kept = spanning_transforms(sessions, dict.fromkeys(accepted_pairs(loops, min_loops)), reachable_only=True)
        dropped = [index for index in T_merged if index not in kept]
        if not dropped:
            factors = {}
            if config.merge.variance_components and 0 in groups:  # relative to the first session's factors
                graph, estimate, factors = reweighted(graph, estimate, weights, groups, 0)
            return graph, estimate, known, loop_factors, factors
        for index in dropped:
            n = sum(1 for lp in loops if index in (lp.target_session, lp.source_session) and lp.weight >= 0.5)
            refused[sessions[index].name] = (
                f"the robust back end kept only {n} of its inter-session loops "
                f"(at least {min_loops} needed with a joined session)"
            )
            del T_merged[index]


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


def _why(
    index: int, votes: dict, conflicts: dict[tuple[int, int], float], loops: list[InterSessionLoop], merge: MergeConfig
) -> str:
    """Why session `index` could not be joined by the votes of its verified loops."""
    mine = [lp for lp in loops if index in (lp.target_session, lp.source_session)]
    if not mine:
        return "no inter-session loop passed verification (the sessions do not seem to overlap)"
    tested = {pair: c for pair, c in conflicts.items() if index in pair}
    if tested:
        pair = min(tested, key=tested.get)
        return (
            f"{len(votes[pair][1])} inter-session loops agree on one transform, but it puts a median "
            f"{100 * tested[pair]:.1f} % of the submap keypoints where the other session saw free space "
            f"(at most {100 * merge.max_free_space_conflict:.1f} %): an aliased place, not an overlap"
        )
    agree = max(len(voters) for pair, (_, voters) in votes.items() if index in pair)
    return (
        f"{len(mine)} inter-session loops passed verification but at most {agree} agree on one transform "
        f"(at least {merge.min_loops} needed)"
    )


def _guided_loops(
    sessions: list[Session],
    T_merged: dict[int, np.ndarray],
    descriptions: Descriptions,
    tried: set[tuple[int, int, int, int]],
    config: SlamConfig,
    map_function: MapFunction,
) -> list[InterSessionLoop]:
    """Register, for every keyframe of a joined session, the nearest keyframe of each earlier joined session
    within `guided_radius` in the merged frame (pairs not tried yet)."""
    pairs = []
    joined = sorted(T_merged)
    positions = {
        i: (
            np.array([T_merged[i] @ sessions[i].keyframe_poses[k][:, 3] for k in descriptions[i]])[:, :3],
            list(descriptions[i]),
        )
        for i in joined
        if descriptions[i]
    }
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
                pairs.append((i, ki, j, kj))
    found = register_pairs(pairs, descriptions, config, "guided", map_function)
    for loop in found:
        i, j = loop.target_session, loop.source_session
        loop.voted = fits(sessions, loop, np.linalg.inv(T_merged[i]) @ T_merged[j], config.merge)
    return found
