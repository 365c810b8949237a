"""A mapping session as the map merger needs it: keyframe submaps, the keyframe graph, every frame's pose."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from sandro_slam.factors import between_factor, gaussian_noise, keyframe_odometry_covariances
from sandro_slam.offline import SlamResult


@dataclass
class SessionEdge:
    """A BetweenFactorPose3 of the session's keyframe graph: T_target_source maps `source` into `target`."""

    target: int
    source: int
    T_target_source: np.ndarray  # 4x4
    covariance: np.ndarray  # 6x6, gtsam order [rotation, translation], right perturbation
    kind: str  # "odometry" or "loop"
    accepted: bool  # loops: the session's robust back end kept it; odometry: always True

    def factor(self, target_key: int, source_key: int) -> gtsam.BetweenFactorPose3:
        """The factor between two graph keys (e.g. the session's keys mapped to gtsam symbols)."""
        return between_factor(target_key, source_key, self.T_target_source, self.covariance)


@dataclass
class Session:
    """One SLAM session in its own world frame (its first scan's, or wherever its poses were expressed).

    keyframe_poses[k]: optimised T_world_keyframe; submaps[k]: (N, 3) points in keyframe k's frame.
    Frame f's pose is keyframe_poses[keyframe_of_frame[f]] @ T_keyframe_frame[f].
    """

    name: str
    keys: list[int]  # keyframe keys in driving order
    keyframe_poses: dict[int, np.ndarray]
    submaps: dict[int, np.ndarray]
    edges: list[SessionEdge]
    timestamps: np.ndarray  # (F,) [s]
    keyframe_of_frame: np.ndarray  # (F,) keyframe key of each frame
    T_keyframe_frame: np.ndarray  # (F, 4, 4) each frame's odometry pose relative to its keyframe
    scale: float | None = None  # the scene scale its configuration used (`SlamConfig.scale`), when known

    @classmethod
    def from_result(cls, result: SlamResult, name: str) -> Session:
        """The session of an `OfflineSlam` run: its keyframes, optimised poses, odometry and loop factors."""
        loop_of_factor = {loop.factor.factor_index: loop for loop in result.loops}
        edges = []
        for index in range(result.graph.size()):
            factor = result.graph.at(index)
            if not isinstance(factor, gtsam.BetweenFactorPose3):
                continue
            target, source = (int(k) for k in factor.keys())
            loop = loop_of_factor.get(index)
            covariance = loop.covariance if loop is not None else np.asarray(gaussian_noise(factor).covariance())
            edges.append(
                SessionEdge(
                    target,
                    source,
                    factor.measured().matrix(),
                    covariance,
                    "odometry" if loop is None else "loop",
                    loop is None or loop.weight >= 0.5,
                )
            )
        return cls(
            name,
            [kf.key for kf in result.keyframes],
            {kf.key: result.keyframe_poses[kf.key] for kf in result.keyframes},
            {kf.key: kf.points for kf in result.keyframes},
            edges,
            result.timestamps.copy(),
            result.keyframe_of_frame.astype(np.int64),
            result.T_keyframe_frame.copy(),
            result.config.scale,
        )

    def keyframe_odometry_covariances(self) -> dict[int, np.ndarray]:
        """Per keyframe key, the 6x6 covariance of the odometry edge across its keyframe: the one that ends at it (the
        first keyframe: the one that starts at it)."""
        return keyframe_odometry_covariances(
            (edge.target, edge.source, edge.covariance) for edge in self.edges if edge.kind == "odometry"
        )

    def frame_poses(self, keyframe_poses: dict[int, np.ndarray] | None = None) -> np.ndarray:
        """(F, 4, 4) T_world_frame of every frame, moved with its keyframe (default: the session's poses)."""
        poses = self.keyframe_poses if keyframe_poses is None else keyframe_poses
        return np.stack([poses[int(k)] for k in self.keyframe_of_frame]) @ self.T_keyframe_frame

    def moved(self, T_new_world: np.ndarray) -> Session:
        """The same session with its poses expressed in another frame (submaps and factors are relative)."""
        poses = {k: T_new_world @ T for k, T in self.keyframe_poses.items()}
        return Session(
            self.name,
            list(self.keys),
            poses,
            self.submaps,
            self.edges,
            self.timestamps,
            self.keyframe_of_frame,
            self.T_keyframe_frame,
            self.scale,
        )

    def check(self) -> None:
        """ValueError naming the first inconsistency (a key without pose or submap, an edge to no keyframe)."""
        if not self.keys:
            raise ValueError(f"session {self.name}: no keyframes")
        known = set(self.keys)
        for key in self.keys:
            if key not in self.keyframe_poses or key not in self.submaps:
                raise ValueError(f"session {self.name}: keyframe {key} has no pose or no submap")
        for edge in self.edges:
            if edge.target not in known or edge.source not in known:
                raise ValueError(f"session {self.name}: an edge refers to unknown keyframe {edge.target}/{edge.source}")
        if not set(np.unique(self.keyframe_of_frame)) <= known:
            raise ValueError(f"session {self.name}: frames refer to unknown keyframes")
