"""LoopClosureModule: the piece another mapping pipeline embeds."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from sandro_slam.candidates import PlaceRecognition, radius_candidates
from sandro_slam.config import SlamConfig
from sandro_slam.factors import odometry_covariance
from sandro_slam.loop_registration import SubmapDescription, describe_submap, register_submaps
from sandro_slam.pose_graph import LoopFactor, PoseGraph


@dataclass
class LoopClosure:
    """A verified loop closure, as added to the graph: points of `source_key`'s submap map into
    `target_key`'s frame by T_target_source."""

    source_key: int
    target_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam Pose3 order [rotation, translation], right perturbation
    inliers: int  # SANDRO inliers among the FPFH matches
    overlap: float  # share of source submap points near the target submap after alignment
    found_by: str  # "radius", "place_recognition" or "radius+place_recognition"
    time_s: float  # registration and verification time
    factor: LoopFactor

    @property
    def weight(self) -> float:
        """The robust back end's weight after the last optimisation (below 0.5: rejected)."""
        return self.factor.weight


class LoopClosureModule:
    """Stores keyframe submaps, finds loop candidates, registers them with SANDRO, verifies them and adds
    them to a gtsam pose graph as BetweenFactorPose3 with the covariance from SANDRO's final weights."""

    def __init__(self, config: SlamConfig | None = None):
        self.config = config or SlamConfig()
        self.pose_graph = PoseGraph(self.config.graph)
        self.loops: list[LoopClosure] = []
        self.attempts = 0  # candidate pairs registered
        self._submaps: dict[int, np.ndarray] = {}  # keyframe submaps (points in the keyframe frame) by key
        self._descriptions: dict[int, SubmapDescription] = {}  # of the submaps, made once each
        self._travelled: dict[int, float] = {}
        self._last_key: int | None = None
        self._place_recognition = PlaceRecognition(self.config.loops) if self.config.loops.use_map_closures else None

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        """Prior, odometry and loop BetweenFactorPose3 factors."""
        return self.pose_graph.graph

    @property
    def values(self) -> gtsam.Values:
        """Initial values: the keyframe poses from odometry."""
        return self.pose_graph.values

    def add_keyframe(
        self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray, odometry_covariance_: np.ndarray | None = None
    ) -> list[LoopClosure]:
        """Add a keyframe at its odometry pose with its submap (points in the keyframe frame).

        The odometry factor links it to the previously added keyframe, with `odometry_covariance_` (6x6,
        gtsam order) or one that grows with the distance travelled. Returns the loops it closed.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"keyframe {key}: points must be an (N, 3) array, got shape {points.shape}")
        finite = np.all(np.isfinite(points), axis=1)
        points = points if finite.all() else points[finite]
        previous = self._last_key
        if previous is None:
            self.pose_graph.add_pose(key, T_world_keyframe)
            self._travelled[key] = 0.0
        else:
            distance = float(np.linalg.norm(T_world_keyframe[:3, 3] - self.values.atPose3(previous).translation()))
            covariance = (
                odometry_covariance(distance, self.config.graph)
                if odometry_covariance_ is None
                else odometry_covariance_
            )
            self.pose_graph.add_pose(key, T_world_keyframe, previous, covariance)
            self._travelled[key] = self._travelled[previous] + distance
        self._last_key = key
        if len(points) < 10:
            return []
        self._submaps[key] = points

        found: dict[int, list[str]] = {}
        positions = {k: self.pose_graph.estimate(k)[:3, 3] for k in self._submaps}
        for other in radius_candidates(key, positions, self._travelled, self.config.loops):
            found.setdefault(other, []).append("radius")
        if self._place_recognition is not None:
            for other in self._place_recognition.candidates(key, points, self._travelled):
                if other in self._submaps:
                    found.setdefault(other, []).append("place_recognition")

        closed = []
        for other, sources in found.items():
            if len(closed) >= self.config.loops.max_loops_per_keyframe:
                break
            self.attempts += 1
            pair = register_submaps(self._description(other), self._description(key), self.config.registration)
            if not pair.accepted:
                continue
            factor = self.pose_graph.add_loop(other, key, pair.T_target_source, pair.covariance)
            closed.append(
                LoopClosure(
                    key,
                    other,
                    pair.T_target_source,
                    pair.covariance,
                    pair.inliers,
                    pair.overlap,
                    "+".join(sources),
                    pair.time_s,
                    factor,
                )
            )
        if closed:
            self.loops.extend(closed)
            # The estimate steers the candidate search of the keyframes to come: re-optimise when a new loop
            # does not hold at it yet.
            if not all(self.pose_graph.holds(loop.factor) for loop in closed):
                self.pose_graph.update_estimate()
        return closed

    def optimize(self) -> dict[int, np.ndarray]:
        """Robustly optimise the graph; T_world_keyframe per key."""
        return self.pose_graph.optimize()

    def rejected_loops(self) -> list[LoopClosure]:
        """Verified loops that the robust back end rejected in the last optimisation."""
        return [loop for loop in self.loops if loop.weight < 0.5]

    def __getstate__(self) -> dict:
        # Descriptions hold Open3D clouds, which do not pickle: `_description` makes them again from the submaps.
        return {**self.__dict__, "_descriptions": {}}

    def _description(self, key: int) -> SubmapDescription:
        description = self._descriptions.get(key)
        if description is None:
            description = self._descriptions[key] = describe_submap(self._submaps[key], self.config.registration)
        return description
