"""The pieces another mapping pipeline embeds: `LoopCloser`, which proposes verified loops for a graph the host owns,
and `LoopClosureModule`, which also keeps the pose graph itself."""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from sandro_core.geometry import rotation_angle
from sandro_slam.candidates import PlaceRecognition, RingKeyRecognition, radius_candidates, span_centres
from sandro_slam.config import SlamConfig
from sandro_slam.factors import between_factor, odometry_covariance
from sandro_slam.loop_registration import (
    MIN_SUBMAP_POINTS,
    SubmapDescription,
    describe_submap,
    register_from_guess,
    register_submaps,
)
from sandro_slam.pose_graph import LoopFactor, PoseGraph

# Submap descriptions kept at once, the most recently used: 1.3-2 MB each at street scale (FPFH keypoints and
# descriptors, the ICP points with normals, the descriptor tree). One evicted is made again from its submap
# (about 40 ms) when a later candidate pair needs it.
MAX_DESCRIPTIONS = 200
AGREEMENT_MAX_ANGLE_DEG = 2.0  # two loops agree within this rotation of the pose the first predicts
GUIDED_MAX_ANGLE_DEG = 0.1  # a guided loop is kept within this rotation of the pose the first loop predicts


@dataclass
class LoopClosure:
    """A verified loop closure: points of `source_key`'s submap map into `target_key`'s frame by T_target_source."""

    source_key: int
    target_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam Pose3 order [rotation, translation], right perturbation
    inliers: int  # SANDRO inliers among the FPFH matches
    overlap: float  # share of source submap points near the target submap after alignment
    found_by: str  # its candidate sources joined by "+": "radius", "place_recognition" (MapClosures), "ring_key";
    # or "guided": registered from the pose the keyframe's agreeing loops predict (`LoopDetectionConfig.guided_loops`)
    time_s: float  # registration and verification time
    factor: LoopFactor | None = None  # its factor in a LoopClosureModule's graph (None for a LoopCloser's loops)

    @property
    def weight(self) -> float:
        """The robust back end's weight after the last optimisation (below 0.5: rejected; nan: in no graph)."""
        return float("nan") if self.factor is None else self.factor.weight

    def between_factor(self, kernel: gtsam.noiseModel.mEstimator.Base | None = None) -> gtsam.BetweenFactorPose3:
        """The loop as a factor for any gtsam graph whose keys are the keyframe keys: BetweenFactorPose3(target_key,
        source_key, T_target_source) with the registration's covariance, wrapped in the robust `kernel` if given."""
        factor = between_factor(self.target_key, self.source_key, self.T_target_source, self.covariance)
        if kernel is None:
            return factor
        robust = gtsam.noiseModel.Robust.Create(kernel, factor.noiseModel())
        return gtsam.BetweenFactorPose3(self.target_key, self.source_key, factor.measured(), robust)


class LoopCloser:
    """Finds loop candidates between keyframes, registers each pair with SANDRO and verifies it; owns no graph.

    The host adds its keyframes (its own keys, its current pose estimates, the submaps) and gets back verified
    loops, each ready to add to its own graph with `LoopClosure.between_factor`. After the host optimises, it hands
    its new estimates back with `update_estimates`: they steer the search for candidates nearby.

    Lengths the configuration leaves None take `config.scale` (1, street scale, when unset): for other scenes pass
    `config.resolved(scene_scale(first_scans))`.
    """

    def __init__(self, config: SlamConfig | None = None):
        self.config = (config or SlamConfig()).resolved()
        self.attempts = 0  # candidate pairs registered
        self._submaps: dict[int, np.ndarray] = {}  # keyframe submaps (points in the keyframe frame) by key
        self._descriptions: dict[int, SubmapDescription] = {}  # of the submaps, least recently used first
        self._estimates: dict[int, np.ndarray] = {}  # current T_world_keyframe by key
        self._travelled: dict[int, float] = {}  # path length [m] at each keyframe
        self._last_key: int | None = None
        self._place_recognition = PlaceRecognition(self.config.loops) if self.config.loops.use_map_closures else None
        self._ring_keys = RingKeyRecognition(self.config.loops) if self.config.loops.ring_key_candidates else None

    def add_keyframe(
        self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray, distance: float | None = None
    ) -> list[LoopClosure]:
        """Add a keyframe at its current estimate T_world_keyframe with its submap (points in the keyframe frame,
        [m]); returns the loops it closes with earlier keyframes, verified. `distance`: the path length [m] from the
        previous keyframe (None: the distance between the two estimates).

        Raises:
            ValueError: points that are not an (N, 3) array, or a key added before.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"keyframe {key}: points must be an (N, 3) array, got shape {points.shape}")
        if key in self._travelled:
            raise ValueError(f"keyframe {key} was added before")
        finite = np.all(np.isfinite(points), axis=1)
        points = points if finite.all() else points[finite]
        previous = self._last_key
        if distance is None:
            distance = (
                0.0
                if previous is None
                else float(np.linalg.norm(T_world_keyframe[:3, 3] - self._estimates[previous][:3, 3]))
            )
        self._travelled[key] = 0.0 if previous is None else self._travelled[previous] + distance
        self._estimates[key] = np.asarray(T_world_keyframe, dtype=np.float64)
        self._last_key = key
        if len(points) < MIN_SUBMAP_POINTS:
            return []
        self._submaps[key] = points
        return self._close_loops(key, points)

    @property
    def keys(self) -> list[int]:
        """Keys of the keyframes that take part in loop closure (those with a submap)."""
        return list(self._submaps)

    def update_estimates(self, T_world_keyframes: dict[int, np.ndarray]) -> None:
        """The host's current estimates of (some of) its keyframes, e.g. after an optimisation."""
        for key, T in T_world_keyframes.items():
            if key in self._estimates:
                self._estimates[key] = np.asarray(T, dtype=np.float64)

    def __getstate__(self) -> dict:
        # Descriptions are not sent along: `_description` makes them again from the submaps when needed.
        return {**self.__dict__, "_descriptions": {}}

    def _close_loops(self, key: int, points: np.ndarray) -> list[LoopClosure]:
        loops = self.config.loops
        found: dict[int, list[str]] = {}
        centres = span_centres({k: self._estimates[k][:3, 3] for k in self._travelled})
        with_submaps = {k: centres[k] for k in self._submaps}
        nearest = radius_candidates(
            key, with_submaps, self._travelled, loops, loops.max_candidates + loops.guided_loops
        )
        for other in nearest[: loops.max_candidates]:
            found.setdefault(other, []).append("radius")
        if self._place_recognition is not None:
            for other in self._place_recognition.candidates(key, points, self._travelled):
                if other in self._submaps:
                    found.setdefault(other, []).append("place_recognition")
        if self._ring_keys is not None:
            for other in self._ring_keys.candidates(key, points, self._travelled):
                found.setdefault(other, []).append("ring_key")
        closed = []
        for other, sources in found.items():
            if len(closed) >= loops.max_loops_per_keyframe:
                break
            self.attempts += 1
            pair = register_submaps(self._description(other), self._description(key), self.config.registration)
            if pair.accepted and self._within_drift(other, key, pair.T_target_source):
                closed.append(LoopClosure(key, other, pair.T_target_source, pair.covariance, pair.inliers,
                                          pair.overlap, "+".join(sources), pair.time_s))  # fmt: skip
        if loops.guided_loops and len(closed) >= 2 and any(self._agrees(closed[0], other) for other in closed[1:]):
            closed += self._guided_loops(closed, nearest)
        return closed

    def _predicted(self, loop: LoopClosure, target: int) -> np.ndarray:
        """T_target_source of `loop`'s source keyframe in keyframe `target`'s frame, through `loop`'s target and the
        current estimates."""
        T_world_source = self._estimates[loop.target_key] @ loop.T_target_source
        return np.linalg.solve(self._estimates[target], T_world_source)

    def _near(self, T_a: np.ndarray, T_b: np.ndarray, max_angle_deg: float) -> bool:
        """Whether two transforms differ by at most `guided_tolerance` [m] and `max_angle_deg`."""
        step = np.linalg.solve(T_a, T_b)
        return bool(
            np.linalg.norm(step[:3, 3]) <= self.config.loops.guided_tolerance
            and np.degrees(rotation_angle(step[:3, :3])) <= max_angle_deg
        )

    def _agrees(self, first: LoopClosure, other: LoopClosure) -> bool:
        """Whether two loops of one keyframe place it alike through the current estimates."""
        return self._near(self._predicted(first, other.target_key), other.T_target_source, AGREEMENT_MAX_ANGLE_DEG)

    def _guided_loops(self, closed: list[LoopClosure], nearest: list[int]) -> list[LoopClosure]:
        """Loops to up to `guided_loops` more of the `nearest` radius candidates, registered by ICP alone from the
        pose the first verified loop predicts, kept at `min_overlap` within the guided tolerance of that pose.

        Only where two loops agree (the caller checks): one wrong loop would place the keyframe wrongly for
        its neighbours too, and their loops, alike wrong, would agree with it and with one another. Each carries
        the first loop's covariance and inliers."""
        first = closed[0]
        source = self._description(first.source_key)
        guided = []
        for other in nearest:
            if len(guided) >= self.config.loops.guided_loops:
                break
            if any(loop.target_key == other for loop in closed):
                continue
            start = time.perf_counter()
            self.attempts += 1
            guess = self._predicted(first, other)
            T, overlap = register_from_guess(self._description(other), source, guess, self.config.registration)
            if overlap >= self.config.registration.min_overlap and self._near(guess, T, GUIDED_MAX_ANGLE_DEG):
                guided.append(LoopClosure(first.source_key, other, T, first.covariance, first.inliers, overlap,
                                          "guided", time.perf_counter() - start))  # fmt: skip
        return guided

    def _within_drift(self, target: int, source: int, T_target_source: np.ndarray) -> bool:
        """Whether the loop places `source` within `radius` + `max_drift` x the path between the two keyframes of
        where the current estimates place it, in the target's frame [m]."""
        estimate = np.linalg.solve(self._estimates[target], self._estimates[source])
        path = abs(self._travelled[source] - self._travelled[target])
        bound = self.config.loops.radius + self.config.loops.max_drift * path
        return bool(np.linalg.norm(T_target_source[:3, 3] - estimate[:3, 3]) <= bound)

    def _description(self, key: int) -> SubmapDescription:
        description = self._descriptions.pop(key, None)
        if description is None:
            description = describe_submap(self._submaps[key], self.config.registration)
            if len(self._descriptions) >= MAX_DESCRIPTIONS:
                del self._descriptions[next(iter(self._descriptions))]
        self._descriptions[key] = description  # the most recently used last
        return description


class LoopClosureModule:
    """A LoopCloser with a pose graph of its own: each keyframe enters the graph with an odometry factor, each
    verified loop as a BetweenFactorPose3 with the covariance from SANDRO's final weights, and the robust back end
    decides which loops to keep. Lengths the configuration leaves None: as `LoopCloser`."""

    def __init__(self, config: SlamConfig | None = None):
        self.config = (config or SlamConfig()).resolved()
        self.closer = LoopCloser(self.config)
        self.pose_graph = PoseGraph(self.config.graph)
        self.loops: list[LoopClosure] = []
        self.estimate_odometry_noise = self.config.graph.estimate_odometry_noise == "always"  # OfflineSlam sets it
        self._last_key: int | None = None

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        """Prior, odometry and loop BetweenFactorPose3 factors."""
        return self.pose_graph.graph

    @property
    def values(self) -> gtsam.Values:
        """Initial values: the keyframe poses from odometry."""
        return self.pose_graph.values

    @property
    def attempts(self) -> int:
        """Candidate pairs registered."""
        return self.closer.attempts

    def add_keyframe(
        self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray, odometry_covariance_: np.ndarray | None = None
    ) -> list[LoopClosure]:
        """Add a keyframe at its odometry pose with its submap (points in the keyframe frame).

        The odometry factor links it to the previously added keyframe, with `odometry_covariance_` (6x6,
        gtsam order) or one that grows with the distance travelled. Returns the loops it closed.
        """
        previous = self._last_key
        distance = None
        if previous is None:
            self.pose_graph.add_pose(key, T_world_keyframe)
        else:
            distance = float(np.linalg.norm(T_world_keyframe[:3, 3] - self.values.atPose3(previous).translation()))
            covariance = (
                odometry_covariance(distance, self.config.graph)
                if odometry_covariance_ is None
                else odometry_covariance_
            )
            self.pose_graph.add_pose(key, T_world_keyframe, previous, covariance)
        self._last_key = key
        # Candidates are searched in the graph's current estimate, which the loops found so far have corrected.
        self.closer.update_estimates({k: self.pose_graph.estimate(k) for k in self.closer.keys})
        closed = self.closer.add_keyframe(key, self.pose_graph.estimate(key), points, distance)
        for loop in closed:
            loop.factor = self.pose_graph.add_loop(loop.target_key, loop.source_key, loop.T_target_source,
                                                   loop.covariance)  # fmt: skip
        if closed:
            self.loops.extend(closed)
            # The estimate steers the candidate search of the keyframes to come: re-optimise when a new loop
            # does not hold at it yet.
            if not all(self.pose_graph.holds(loop.factor) for loop in closed):
                self.pose_graph.update_estimate()
        return closed

    def optimize(self) -> dict[int, np.ndarray]:
        """Robustly optimise the graph (then, with `estimate_odometry_noise`, the odometry covariances scaled to fit
        the loops kept); T_world_keyframe per key."""
        return self.pose_graph.optimize(self.estimate_odometry_noise)

    def rejected_loops(self) -> list[LoopClosure]:
        """Verified loops that the robust back end rejected in the last optimisation."""
        return [loop for loop in self.loops if loop.weight < 0.5]
