"""The keyframe pose graph: prior, odometry and loop factors, optimised robustly (batch or ISAM2)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from sandro_slam.config import GraphConfig


@dataclass
class LoopFactor:
    """A loop factor in the graph: BetweenFactorPose3(target_key, source_key, T_target_source)."""

    factor_index: int
    target_key: int
    source_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam order [rotation, translation], right perturbation of T_target_source
    weight: float = 1.0  # robust back end's weight after the last optimisation (1 = inlier)


def odometry_covariance(distance: float, config: GraphConfig) -> np.ndarray:
    """6x6 covariance of an odometry factor over `distance` metres: std growing linearly with travel."""
    rot = config.odometry_rotation_sigma_per_m * distance + config.odometry_sigma_floor
    trans = config.odometry_translation_sigma_per_m * distance + config.odometry_sigma_floor
    return np.diag([rot**2] * 3 + [trans**2] * 3)


def between_factor(key_a: int, key_b: int, T_a_b: np.ndarray, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """BetweenFactorPose3 measuring T_a_b, with a covariance of its right (body-frame) perturbation."""
    return gtsam.BetweenFactorPose3(key_a, key_b, gtsam.Pose3(T_a_b), gtsam.noiseModel.Gaussian.Covariance(covariance))


def gaussian_noise(factor: gtsam.NoiseModelFactor) -> gtsam.noiseModel.Base:
    """A factor's noise model, or the Gaussian a robust model wraps."""
    model = factor.noiseModel()
    return model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model


GNC_LM_ITERATIONS = 5  # LM iterations per GNC step (gtsam: 100)
GNC_LM_RELATIVE_TOL = 1e-3  # LM relative cost decrease that ends a GNC step (gtsam: 1e-5)
GNC_WEIGHTS_TOL = 0.0  # GNC-TLS ends early when every weight is within this of 0 or 1 (gtsam: 1e-4). A wrong loop
# with a tight covariance leaves a huge residual in GNC's first, least-squares solution; the control parameter
# starts tiny in proportion, and every other loop's weight starts near 0 (3e-4 for a real loop on the simulated
# drive), which at 1e-4 passed for converged: GNC stopped after one step, all loops rejected
GNC_MU_STEP = {"gnc_tls": 2.0, "gnc_gm": 1.4}  # factor on GNC's control parameter per step (gtsam: 1.4; GM at
# 2.0 rejected real loops of kitti_00)
REFINE_RELATIVE_TOL = 1e-10  # of the final LM on the kept factors: soft graphs (parking-garage) move metres
# for a relative cost change of 1e-5, gtsam's default
MIN_LOOPS_FOR_SCALE = 10  # kept loops needed to estimate their variance factor
MIN_KEPT_SHARE = 0.8  # noise_scale 'estimated': of the first run's loops, the scaled run must keep more than this
# (parking-garage: 99 %, its outliers are few among what the first run kept; the demo drive: 55 %, dropping 10
# real loops whose small common bias the others did not share; at 0.5 that run won on some runs)
MIN_FIT_GAIN = 2.0  # and fit those it keeps this much better (median squared error) than the first run
READMIT_SIGMAS = 7.0  # noise_scale 'estimated': a rejected loop comes back when its log squared error is within
# this many robust standard deviations of the kept loops' (parking-garage: real loops reach 4.7, outliers start
# at 10)


def robust_optimize(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int],
                    config: GraphConfig) -> tuple[gtsam.Values, np.ndarray]:
    """Optimise `graph` with the configured robust back end; returns the values and a weight per factor
    (1 for known inliers; below 0.5 means rejected).

    gnc_tls / gnc_gm: gtsam's GncLMOptimizer, with `known_inliers` (prior and odometry factor indices)
    never down-weighted and the inlier threshold at `inlier_probability` of the chi-square of each factor's
    dimension, then Levenberg-Marquardt to convergence (`REFINE_RELATIVE_TOL`) on the factors it kept. GNC
    runs a short LM (`GNC_LM_ITERATIONS`, relative tolerance `GNC_LM_RELATIVE_TOL`) per step of its control
    parameter, which changes by `GNC_MU_STEP`: each step starts from the last, so the steps together still
    converge (TLS on sphere2500 with 10 % outlier loops: the same result as gtsam's defaults of 100 iterations,
    1e-5 and 1.4, 4x faster). GM ends when its control parameter reaches 1, not on gtsam's relative cost test,
    which stopped it in its first, near-convex steps with every weight still 1. TLS ends on its control
    parameter or cost, not when its weights look binary (`GNC_WEIGHTS_TOL`).
    With `noise_scale: estimated`, for graphs whose covariances are not to scale: when the loops the first run
    kept fit better than their covariances say (`variance_factor` below 1), a second GNC run takes the
    threshold times that factor, loops it rejected that fit as well as the heavy tail of those it kept come
    back (`readmitted`), and its result replaces the first when it keeps more than `MIN_KEPT_SHARE` of the
    loops the first kept and fits them clearly better (`_scaled_run_wins`). Graphs whose loops differ in
    dimension keep the first run (gtsam takes one threshold).
    none: plain Levenberg-Marquardt, every weight 1.
    """
    if config.robust == "none":
        return gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize(), np.ones(graph.size())
    values, weights = _gnc(graph, initial, known_inliers, config)
    values = _refined(graph, values, weights)
    dims = {graph.at(int(i)).dim() for i in _loop_indices(graph.size(), known_inliers)}
    if config.noise_scale == "estimated" and len(dims) == 1:
        scale = variance_factor(graph, values, weights, known_inliers)
        if scale < 1.0:  # 1: too few loops to tell; above 1 the stated covariances are not too loose
            threshold = 0.5 * chi2.ppf(config.inlier_probability, dims.pop()) * scale
            scaled_values, scaled_weights = _gnc(graph, initial, known_inliers, config, threshold)
            scaled_weights = readmitted(graph, scaled_values, scaled_weights, known_inliers)
            scaled_values = _refined(graph, scaled_values, scaled_weights)
            if _scaled_run_wins(graph, values, weights, scaled_values, scaled_weights, known_inliers):
                values, weights = scaled_values, scaled_weights
    return values, weights


def _refined(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray) -> gtsam.Values:
    """Levenberg-Marquardt to convergence (`REFINE_RELATIVE_TOL`) on the factors of weight >= 0.5."""
    kept = gtsam.NonlinearFactorGraph()
    for index in np.flatnonzero(weights >= 0.5):
        kept.add(graph.at(int(index)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(REFINE_RELATIVE_TOL)
    params.setAbsoluteErrorTol(0.0)
    return gtsam.LevenbergMarquardtOptimizer(kept, values, params).optimize()


def variance_factor(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray,
                    known_inliers: list[int]) -> float:
    """Robust estimate of how much smaller (< 1) or larger the kept loops' squared whitened errors at `values`
    are than their covariances say: their median over the chi-square median of their dimension. 1 with fewer
    than `MIN_LOOPS_FOR_SCALE` kept loops.

    Example: parking-garage's loops state 1 m and 29 deg standard deviations and fit to millimetres; with
    those covariances any wrong loop within a few metres of the truth passes as an inlier.
    """
    loops = _loop_indices(graph.size(), known_inliers)
    kept = loops[weights[loops] >= 0.5]
    if len(kept) < MIN_LOOPS_FOR_SCALE:
        return 1.0
    factors = [graph.at(int(i)) for i in kept]
    whitened = [2.0 * factor.error(values) / chi2.median(factor.dim()) for factor in factors]
    return float(np.median(whitened))


def readmitted(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray,
               known_inliers: list[int]) -> np.ndarray:
    """`weights` with weight 1 for every loop whose squared whitened error at `values` lies within
    `READMIT_SIGMAS` robust standard deviations (1.4826 x median absolute deviation, in log10) above the
    median of the kept loops'; the others keep their weight.

    A threshold at a chi-square quantile of the estimated scale cuts real loops when their errors are
    heavy-tailed: parking-garage's largest is 200x their median (4615 chi-square draws: about 5x), the
    outliers' smallest 10^5x. In log space that tail is 4.7 robust sigmas, the outliers 10.
    """
    loops = _loop_indices(graph.size(), known_inliers)
    log_error = np.log10([max(2.0 * graph.at(int(i)).error(values), 1e-300) for i in loops])
    kept = weights[loops] >= 0.5
    if kept.sum() < MIN_LOOPS_FOR_SCALE:
        return weights
    median = np.median(log_error[kept])
    sigma = 1.4826 * np.median(np.abs(log_error[kept] - median))
    out = weights.copy()
    out[loops[log_error <= median + READMIT_SIGMAS * sigma]] = 1.0
    return out


def _scaled_run_wins(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray,
                     scaled_values: gtsam.Values, scaled_weights: np.ndarray, known_inliers: list[int]) -> bool:
    """Whether the scaled run's result replaces the first run's. It must keep more than `MIN_KEPT_SHARE` of
    the loops the first run kept: what it is for is the few outliers that loose covariances let pass, and a
    threshold that rejects many of the first run's loops cuts their own heavy tail (kitti_00: 34 of 137 real
    loops kept) or real loops with a small shared bias (the demo drive: 12 of 22 kept). And the loops both
    runs kept must fit at least `MIN_FIT_GAIN` times better (median squared error) without the ones it
    dropped: those were bending the graph (parking-garage at 10 % outliers: 22x better), not just the tail of
    the real loops (sphere2500: one real loop dropped, the others fit as well as before, the poses 3.5 % off).
    """
    loops = _loop_indices(len(weights), known_inliers)
    kept = loops[weights[loops] >= 0.5]
    both = kept[scaled_weights[kept] >= 0.5]
    if len(both) <= MIN_KEPT_SHARE * len(kept):
        return False
    first_fit = np.median([graph.at(int(i)).error(values) for i in both])
    scaled_fit = np.median([graph.at(int(i)).error(scaled_values) for i in both])
    return bool(scaled_fit * MIN_FIT_GAIN <= first_fit)


def _loop_indices(size: int, known_inliers: list[int]) -> np.ndarray:
    """Indices of the factors the robust back end judges, of a graph of `size`: all but the known inliers."""
    known = set(known_inliers)
    return np.array([i for i in range(size) if i not in known], dtype=int)


def _gnc(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int], config: GraphConfig,
         threshold: float | None = None) -> tuple[gtsam.Values, np.ndarray]:
    """GncLMOptimizer with the inlier cost threshold (half the squared whitened error) at `threshold` for every
    loop, or at `inlier_probability` of the chi-square of each loop's dimension when None."""
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(GNC_LM_ITERATIONS)
    lm_params.setRelativeErrorTol(GNC_LM_RELATIVE_TOL)
    params = gtsam.GncLMParams(lm_params)
    params.setLambdaStep(GNC_MU_STEP[config.robust])
    if config.robust == "gnc_tls":
        params.setLossType(gtsam.GncLossType.TLS)
        params.setWeightsTol(GNC_WEIGHTS_TOL)
    else:
        params.setLossType(gtsam.GncLossType.GM)
        params.setRelativeCostTol(0.0)
    params.setKnownInliers(known_inliers)
    optimizer = gtsam.GncLMOptimizer(graph, initial, params)
    if threshold is None:
        optimizer.setInlierCostThresholdsAtProbability(config.inlier_probability)
    else:
        optimizer.setInlierCostThresholds(threshold)
    values = optimizer.optimize()
    return values, np.asarray(optimizer.getWeights())


class PoseGraph:
    """Keyframe poses T_world_keyframe under a prior on the first, odometry chains and loop closures.

    The prior and the odometry factors are known inliers; loops are judged by the robust back end
    (`GraphConfig.robust`): graduated non-convexity (gtsam GncLMOptimizer, TLS or Geman-McClure)
    decides which loops are outliers. In incremental mode ISAM2 keeps the estimate and holds the loops the
    robust back end accepts.
    """

    def __init__(self, config: GraphConfig):
        self.config = config
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()  # initial values: the odometry chain
        self.loops: list[LoopFactor] = []
        self._known_inliers: list[int] = []
        self._estimate = gtsam.Values()
        self._isam = gtsam.ISAM2() if config.mode == "incremental" else None
        self._isam_slots: dict[int, int] = {}  # graph factor index -> ISAM2 factor slot (accepted loops)

    def add_pose(self, key: int, T_world_keyframe: np.ndarray, odometry_from: int | None = None,
                 odometry_covariance_: np.ndarray | None = None) -> None:
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

    def add_loop(self, target_key: int, source_key: int, T_target_source: np.ndarray,
                 covariance: np.ndarray) -> LoopFactor:
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

    def optimize(self) -> dict[int, np.ndarray]:
        """Optimise; returns T_world_keyframe per key and updates each loop's weight."""
        if self.values.size() == 0:
            return {}
        if self._isam is not None:
            self._optimize_incremental()
        else:
            self._estimate = self._robust_optimize(self.values)
        return {key: self._estimate.atPose3(key).matrix() for key in self._estimate.keys()}

    def update_estimate(self) -> None:
        """Re-optimise for the estimate alone, cheaper than `optimize`, which decides the loops afresh: in batch
        mode from the latest estimate rather than the odometry, and with the stated loop covariances
        (noise_scale 'given': no second GNC run). What the loop closure module needs to steer its candidate
        search between keyframes."""
        if self._isam is not None:
            self._optimize_incremental()
        elif self.values.size() > 0:
            given = self.config.model_copy(update={"noise_scale": "given"})
            self._estimate = self._robust_optimize(self._estimate, given)

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
        for index in self._known_inliers + accepted:
            factors.add(self.graph.at(index))
        slots = list(self._isam.update(factors, self._estimate).getNewFactorsIndices())
        self._isam_slots = dict(zip(accepted, slots[len(self._known_inliers):]))

    def _robust_optimize(self, initial: gtsam.Values, config: GraphConfig | None = None) -> gtsam.Values:
        if not self.loops:
            return gtsam.LevenbergMarquardtOptimizer(self.graph, initial).optimize()
        result, weights = robust_optimize(self.graph, initial, self._known_inliers, config or self.config)
        for loop in self.loops:
            loop.weight = float(weights[loop.factor_index])
        return result

    def _optimize_incremental(self) -> None:
        """GNC on the whole graph decides which loops hold; ISAM2 gets the newly accepted ones and drops
        the newly rejected ones."""
        self._robust_optimize(self._isam.calculateEstimate())
        added = [loop for loop in self.loops if loop.weight >= 0.5 and loop.factor_index not in self._isam_slots]
        removed = [self._isam_slots.pop(loop.factor_index) for loop in self.loops
                   if loop.weight < 0.5 and loop.factor_index in self._isam_slots]
        if added or removed:
            new_factors = gtsam.NonlinearFactorGraph()
            for loop in added:
                new_factors.add(self.graph.at(loop.factor_index))
            result = self._isam.update(new_factors, gtsam.Values(), removed)
            for loop, slot in zip(added, result.getNewFactorsIndices()):
                self._isam_slots[loop.factor_index] = slot
        self._isam.update()
        self._estimate = self._isam.calculateEstimate()
