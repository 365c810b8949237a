"""The merged pose graph over the joined sessions, and the merge's result."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from sandro_slam.factors import between_factor, widened_loop_covariance
from sandro_slam.merge.loops import InterSessionLoop
from sandro_slam.session import Session


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
    graph: gtsam.NonlinearFactorGraph  # the merged graph (keys: session_key), its loops as the estimate weighs them
    values: gtsam.Values  # its optimised values
    timings: dict[str, float] = field(default_factory=dict)  # seconds
    # `merge.variance_components`: the variance factor of each session's factors (by its name) and of the
    # inter-session loops ("inter-session loops"), relative to the first session's; empty without it
    variance_factors: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when every session was joined."""
        return not self.refused


INTER_SESSION = -1  # the variance components' group of every inter-session loop; a session's factors: its index


def session_key(session_index: int, key: int) -> int:
    """The merged graph's key of keyframe `key` of session `session_index`."""
    return gtsam.symbol(chr(ord("a") + session_index), key)


def build_graph(
    sessions: list[Session],
    T_merged: dict[int, np.ndarray],
    loops: list[InterSessionLoop],
    prior_sigma: float,
    loop_submap_noise: bool = False,
):
    """The merged graph over the joined sessions: (graph, initial values, known inlier factor indices,
    [(loop, factor index)] of the inter-session loops, each factor's group: its session's index, `INTER_SESSION`
    or None for the prior). With `loop_submap_noise` the same factors at the same indices, but each loop, the
    sessions' and the inter-session ones, with its covariance plus the odometry covariance across each of its two
    keyframes (`factors.widened_loop_covariance`, as `PoseGraph` weighs them)."""
    graph, values, known, groups = gtsam.NonlinearFactorGraph(), gtsam.Values(), [], []
    prior = gtsam.noiseModel.Isotropic.Sigma(6, prior_sigma)
    across = {index: sessions[index].keyframe_odometry_covariances() for index in T_merged} if loop_submap_noise else {}

    def covariance(loop_covariance: np.ndarray, target: tuple[int, int], source: tuple[int, int]) -> np.ndarray:
        """`loop_covariance`, widened with `loop_submap_noise`; target and source: (session index, key)."""
        if not loop_submap_noise:
            return loop_covariance
        return widened_loop_covariance(
            loop_covariance, *(across[session].get(key) for session, key in (target, source))
        )

    for index in sorted(T_merged):
        session = sessions[index]
        for key in session.keys:
            values.insert(session_key(index, key), gtsam.Pose3(T_merged[index] @ session.keyframe_poses[key]))
        if index == 0:
            first = session_key(0, session.keys[0])
            known.append(graph.size())
            groups.append(None)
            graph.add(gtsam.PriorFactorPose3(first, values.atPose3(first), prior))
        for edge in session.edges:
            if edge.accepted:
                known.append(graph.size())
                edge_covariance = (
                    edge.covariance
                    if edge.kind == "odometry"
                    else covariance(edge.covariance, (index, edge.target), (index, edge.source))
                )
                target, source = session_key(index, edge.target), session_key(index, edge.source)
                groups.append(index)
                graph.add(between_factor(target, source, edge.T_target_source, edge_covariance))
    loop_factors = []
    for loop in loops:
        if loop.voted and loop.target_session in T_merged and loop.source_session in T_merged:
            loop_factors.append((loop, graph.size()))
            groups.append(INTER_SESSION)
            graph.add(
                between_factor(
                    session_key(loop.target_session, loop.target_key),
                    session_key(loop.source_session, loop.source_key),
                    loop.T_target_source,
                    covariance(
                        loop.covariance,
                        (loop.target_session, loop.target_key),
                        (loop.source_session, loop.source_key),
                    ),
                )
            )
    return graph, values, known, loop_factors, groups


def group_name(group: int, sessions: list[Session]) -> str:
    """A readable name of a factor group: its session's name, or "inter-session loops"."""
    return "inter-session loops" if group == INTER_SESSION else sessions[group].name


def accepted_pairs(loops: list[InterSessionLoop], min_loops: int) -> list[tuple[int, int]]:
    """Session pairs joined by at least `min_loops` inter-session loops the back end kept."""
    counts: dict[tuple[int, int], int] = {}
    for loop in loops:
        if loop.weight >= 0.5:
            pair = (loop.target_session, loop.source_session)
            counts[pair] = counts.get(pair, 0) + 1
    return [pair for pair, n in counts.items() if n >= min_loops]


def merge_result(
    sessions: list[Session],
    T_merged: dict[int, np.ndarray],
    refused: dict[str, str],
    loops: list[InterSessionLoop],
    graph: gtsam.NonlinearFactorGraph,
    estimate: gtsam.Values,
    known: list[int],
    loop_factors: list[tuple[InterSessionLoop, int]],
) -> MergeResult:
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
