"""The keyframe pose graph: prior, odometry and loop factors, optimised robustly (batch or ISAM2)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from sandro_slam.config import GraphConfig
from sandro_slam.factors import between_factor, gaussian_noise, keyframe_odometry_covariances, widened_loop_covariance
from sandro_slam.noise_scale import rescale_odometry
from sandro_slam.robust_backend import refined, robust_optimize


@dataclass
class LoopFactor:
    """A loop factor in the graph: BetweenFactorPose3(target_key, source_key, T_target_source)."""

    factor_index: int
    target_key: int
    source_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam order [rotation, translation], right perturbation of T_target_source
    weight: float = 1.0  # robust back end's weight after the last optimisation (1 = inlier)


class PoseGraph:
    """Keyframe poses T_world_keyframe under a prior on the first, odometry chains and loop closures.

    The prior and the odometry factors are known inliers; the robust back end (`GraphConfig.robust`,
    `robust_backend.robust_optimize`: truncated least squares seeded by the loops that agree with their
    neighbours, or gtsam's GNC) decides which loops are outliers. In incremental mode ISAM2 keeps the estimate
    and holds the loops the robust back end accepts.

    With `loop_submap_noise`, the estimate is solved, once the loops are decided, with each kept loop's covariance
    widened by the odometry covariance of each of its two keyframes (`factors.widened_loop_covariance`): a loop
    aligns two submaps, and each is only as rigid as the odometry that built it.
    """

    def __init__(self, config: GraphConfig):
        self.config = config
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()  # initial values: the odometry chain
        self.loops: list[LoopFactor] = []
        self.odometry_scale = 1.0  # on the odometry covariances in the last optimisation (noise_scale)
        self._known_inliers: list[int] = []
        self._estimate = gtsam.Values()
        self._isam = gtsam.ISAM2() if config.mode == "incremental" else None
        self._isam_slots: dict[int, int] = {}  # graph factor index -> ISAM2 factor slot (accepted loops)
        self._weights = np.ones(0)  # the robust back end's weight per factor in the last optimisation

    def add_pose(
        self,
        key: int,
        T_world_keyframe: np.ndarray,
        odometry_from: int | None = None,
        odometry_covariance_: np.ndarray | None = None,
    ) -> None:
        """Add a keyframe at its odometry pose: the first gets the prior, the others an odometry factor
        from `odometry_from` measuring the relative odometry pose, with `odometry_covariance_` (6x6)."""
        if self.values.exists(key):
            raise ValueError(f"keyframe {key} is already in the graph")
        pose = gtsam.Pose3(T_world_keyframe)
        if odometry_from is None:
            if self.values.size() > 0:
                raise ValueError("only the first keyframe may come without odometry")
            factor = gtsam.PriorFactorPose3(key, pose, gtsam.noiseModel.Isotropic.Sigma(6, self.config.prior_sigma))
            initial = pose
        else:
            previous = self.values.atPose3(odometry_from)
            T_prev_key = previous.between(pose).matrix()
            factor = between_factor(odometry_from, key, T_prev_key, odometry_covariance_)
            # Start from the current estimate of the previous keyframe so new poses follow the corrections.
            prev_estimate = self._estimate.atPose3(odometry_from) if self._estimate.exists(odometry_from) else previous
            initial = prev_estimate.compose(gtsam.Pose3(T_prev_key))
        self._known_inliers.append(self.graph.size())
        self.graph.add(factor)
        self.values.insert(key, pose)
        self._estimate.insert(key, initial)
        if self._isam is not None:
            new_factors = gtsam.NonlinearFactorGraph()
            new_factors.add(factor)
            new_values = gtsam.Values()
            new_values.insert(key, initial)
            self._isam.update(new_factors, new_values)
            self._estimate = self._isam.calculateEstimate()

    def add_loop(
        self, target_key: int, source_key: int, T_target_source: np.ndarray, covariance: np.ndarray
    ) -> LoopFactor:
        """Add BetweenFactorPose3(target_key, source_key) measuring T_target_source with the registration's
        covariance (gtsam order and frame, as `sandro_core` returns it)."""
        for key in (target_key, source_key):
            if not self.values.exists(key):
                raise ValueError(f"loop refers to unknown keyframe {key}")
        if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
            raise ValueError("a loop needs a finite 6x6 covariance")
        loop = LoopFactor(self.graph.size(), target_key, source_key, T_target_source, covariance)
        self.graph.add(between_factor(target_key, source_key, T_target_source, covariance))
        self.loops.append(loop)
        return loop

    def optimize(self, estimate_odometry_noise: bool = False) -> dict[int, np.ndarray]:
        """Optimise; returns T_world_keyframe per key and updates each loop's weight. The kept loops weigh in the
        estimate as `_estimation_factors` makes them. With `estimate_odometry_noise`, the odometry covariances are then
        scaled to fit the loops the robust back end kept (`noise_scale.rescale_odometry`; the factor in
        `odometry_scale`)."""
        if self.values.size() == 0:
            return {}
        if self._isam is not None:
            self._optimize_incremental()
        else:
            self._estimate = self._with_loop_submap_noise(self._robust_optimize(self.values))
        if estimate_odometry_noise:
            odometry = self._known_inliers[1:]  # the first is the prior
            kept = [loop.factor_index for loop in self.loops if loop.weight >= 0.5]
            self._estimate, self.odometry_scale = rescale_odometry(
                self._estimation_graph(), self._estimate, odometry, kept
            )
        return {key: self._estimate.atPose3(key).matrix() for key in self._estimate.keys()}

    def update_estimate(self) -> None:
        """Re-optimise for the estimate alone, cheaper than `optimize`, which decides the loops afresh: in batch
        mode from the latest estimate rather than the odometry, and with the stated loop covariances
        (noise_scale 'given': no second GNC run), the kept loops then weighing as in `optimize`. What the loop
        closure module needs to steer its candidate search between keyframes."""
        if self._isam is not None:
            self._optimize_incremental()
        elif self.values.size() > 0:
            given = self.config.model_copy(update={"noise_scale": "given"})
            self._estimate = self._with_loop_submap_noise(self._robust_optimize(self._estimate, given))

    def estimate(self, key: int) -> np.ndarray:
        """The latest estimate of T_world_keyframe for `key`."""
        return self._estimate.atPose3(key).matrix()

    def holds(self, loop: LoopFactor) -> bool:
        """Whether `loop` already holds at the latest estimate: its whitened error is within the robust back
        end's inlier threshold (the chi-square of 6 degrees of freedom at `inlier_probability`)."""
        error = self.graph.at(loop.factor_index).error(self._estimate)  # half the squared whitened error
        return error <= 0.5 * chi2.ppf(self.config.inlier_probability, 6)

    def rejected_loops(self) -> list[LoopFactor]:
        """Loops the robust back end weighted below 0.5 in the last optimisation."""
        return [loop for loop in self.loops if loop.weight < 0.5]

    def __getstate__(self) -> dict:
        # gtsam.ISAM2 does not pickle: `__setstate__` builds it again.
        return {**self.__dict__, "_isam": None}

    def __setstate__(self, state: dict) -> None:
        """Unpickle; in incremental mode, a new ISAM2 holds the prior, the odometry and the accepted loops, linearised
        at the latest estimate."""
        self.__dict__.update(state)
        if self.config.mode != "incremental":
            return
        self._isam = gtsam.ISAM2()
        if self._estimate.size() == 0:
            return
        factors = gtsam.NonlinearFactorGraph()
        accepted = sorted(self._isam_slots)
        for index in self._known_inliers:
            factors.add(self.graph.at(index))
        by_index = {loop.factor_index: loop for loop in self.loops}
        for factor in self._estimation_factors([by_index[index] for index in accepted]):
            factors.add(factor)
        slots = list(self._isam.update(factors, self._estimate).getNewFactorsIndices())
        self._isam_slots = dict(zip(accepted, slots[len(self._known_inliers) :]))

    def _with_loop_submap_noise(self, values: gtsam.Values) -> gtsam.Values:
        """Batch mode with `loop_submap_noise`: `values` solved again on the factors the robust back end kept,
        each loop as `_estimation_factors` makes it."""
        if not self.config.loop_submap_noise or not any(loop.weight >= 0.5 for loop in self.loops):
            return values
        return refined(self._estimation_graph(), values, self._weights)

    def _estimation_graph(self) -> gtsam.NonlinearFactorGraph:
        """The graph with each loop's factor at its index replaced as `_estimation_factors` makes it."""
        if not self.config.loop_submap_noise:
            return self.graph
        graph = self.graph.clone()
        for loop, factor in zip(self.loops, self._estimation_factors(self.loops)):
            graph.replace(loop.factor_index, factor)
        return graph

    def _estimation_factors(self, loops: list[LoopFactor]) -> list[gtsam.BetweenFactorPose3]:
        """The loops' factors as the estimate weighs them once loops are decided: with `loop_submap_noise`, each
        covariance widened by the odometry across its two keyframes (`factors.widened_loop_covariance`); else their
        own."""
        if not self.config.loop_submap_noise:
            return [self.graph.at(loop.factor_index) for loop in loops]
        odometry = (self.graph.at(index) for index in self._known_inliers[1:])  # the first is the prior
        across = keyframe_odometry_covariances(
            (*factor.keys(), gaussian_noise(factor).covariance()) for factor in odometry
        )
        return [
            between_factor(
                loop.target_key,
                loop.source_key,
                loop.T_target_source,
                widened_loop_covariance(loop.covariance, across.get(loop.target_key), across.get(loop.source_key)),
            )
            for loop in loops
        ]

    def _robust_optimize(self, initial: gtsam.Values, config: GraphConfig | None = None) -> gtsam.Values:
        if not self.loops:
            self._weights = np.ones(self.graph.size())
            return gtsam.LevenbergMarquardtOptimizer(self.graph, initial).optimize()
        result, weights = robust_optimize(self.graph, initial, self._known_inliers, config or self.config)
        self._weights = weights
        for loop in self.loops:
            loop.weight = float(weights[loop.factor_index])
        return result

    def _optimize_incremental(self) -> None:
        """The robust back end on the whole graph decides which loops hold; ISAM2 gets the newly accepted ones and drops
        the newly rejected ones."""
        self._robust_optimize(self._isam.calculateEstimate())
        added = [loop for loop in self.loops if loop.weight >= 0.5 and loop.factor_index not in self._isam_slots]
        removed = [
            self._isam_slots.pop(loop.factor_index)
            for loop in self.loops
            if loop.weight < 0.5 and loop.factor_index in self._isam_slots
        ]
        if added or removed:
            new_factors = gtsam.NonlinearFactorGraph()
            for factor in self._estimation_factors(added):
                new_factors.add(factor)
            result = self._isam.update(new_factors, gtsam.Values(), removed)
            for loop, slot in zip(added, result.getNewFactorsIndices()):
                self._isam_slots[loop.factor_index] = slot
        self._isam.update()
        self._estimate = self._isam.calculateEstimate()
