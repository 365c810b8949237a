"""The robust back end: which loop factors of a pose graph to keep, by graduated non-convexity (gtsam GNC).

The prior and odometry factors are known inliers; every other factor is a loop the back end may reject. See
docs/back-end.md for the measurements behind the settings below.
"""

from __future__ import annotations

import gtsam
import numpy as np
from scipy.stats import chi2

from sandro_slam.config import GraphConfig

GNC_LM_ITERATIONS = 5  # LM iterations per GNC step (gtsam: 100): each step starts from the last
GNC_LM_RELATIVE_TOL = 1e-3  # LM relative cost decrease that ends a GNC step (gtsam: 1e-5)
GNC_WEIGHTS_TOL = 0.0  # TLS: never end early because every weight is within this of 0 or 1 (gtsam: 1e-4). A wrong
# loop with a tight covariance makes GNC's first control parameter tiny, which leaves every real loop's weight
# near 0 at the start: that must not pass for converged
GNC_MU_STEP = {"gnc_tls": 2.0, "gnc_gm": 1.4}  # factor on GNC's control parameter per step (gtsam: 1.4)
REFINE_RELATIVE_TOL = 1e-10  # of the final LM on the kept factors: on graphs with loose covariances poses move
# metres for a relative cost change of gtsam's default 1e-5
MIN_LOOPS_FOR_SCALE = 10  # kept loops needed to estimate their variance factor
MIN_KEPT_SHARE = 0.8  # noise_scale 'estimated': of the first run's loops, the scaled run must keep more than this
MIN_FIT_GAIN = 2.0  # and fit those it keeps this much better (median squared error) than the first run
READMIT_SIGMAS = 7.0  # noise_scale 'estimated': a rejected loop comes back when its log squared error is within
# this many robust standard deviations of the kept loops'


def robust_optimize(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int], config: GraphConfig
) -> tuple[gtsam.Values, np.ndarray]:
    """Optimise `graph` with the configured robust back end; returns the values and a weight per factor
    (1 for known inliers; below 0.5 means rejected).

    gnc_tls / gnc_gm: gtsam's GncLMOptimizer, with `known_inliers` (prior and odometry factor indices)
    never down-weighted and the inlier threshold at `inlier_probability` of the chi-square of each factor's
    dimension, then Levenberg-Marquardt to convergence (`REFINE_RELATIVE_TOL`) on the factors it kept. GNC
    runs a short LM (`GNC_LM_ITERATIONS`, relative tolerance `GNC_LM_RELATIVE_TOL`) per step of its control
    parameter, which changes by `GNC_MU_STEP`: each step starts from the last, so the steps together still
    converge. GM ends when its control parameter reaches 1, not on gtsam's relative cost test, which can stop
    it in its first, near-convex steps with every weight still 1. TLS ends on its control parameter or cost,
    not when its weights look binary (`GNC_WEIGHTS_TOL`).
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


def check_loops(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, loop_indices: list[int], config: GraphConfig | None = None
) -> tuple[np.ndarray, gtsam.Values]:
    """Which loop factors of a graph someone else built to keep: the robust back end (`robust_optimize`) on the whole
    graph, with every factor but those at `loop_indices` (odometry, IMU, GPS, priors) as a known inlier.

    Returns:
        (keep: (L,) bool per entry of `loop_indices`, the values optimised with the kept loops).
    """
    loop_indices = [int(i) for i in loop_indices]
    if not loop_indices:
        return np.zeros(0, dtype=bool), gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    chosen = set(loop_indices)
    known = [i for i in range(graph.size()) if i not in chosen]
    optimized, weights = robust_optimize(graph, values, known, config or GraphConfig())
    return weights[loop_indices] >= 0.5, optimized


def _refined(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray) -> gtsam.Values:
    """Levenberg-Marquardt to convergence (`REFINE_RELATIVE_TOL`) on the factors of weight >= 0.5."""
    kept = gtsam.NonlinearFactorGraph()
    for index in np.flatnonzero(weights >= 0.5):
        kept.add(graph.at(int(index)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(REFINE_RELATIVE_TOL)
    params.setAbsoluteErrorTol(0.0)
    return gtsam.LevenbergMarquardtOptimizer(kept, values, params).optimize()


def variance_factor(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray, known_inliers: list[int]
) -> float:
    """Robust estimate of how much smaller (< 1) or larger the kept loops' squared whitened errors at `values`
    are than their covariances say: their median over the chi-square median of their dimension. 1 with fewer
    than `MIN_LOOPS_FOR_SCALE` kept loops.

    Loops whose covariances overstate their noise (they state metres and fit to millimetres) let any wrong loop
    within a few metres of the truth pass as an inlier: their variance factor is far below 1.
    """
    loops = _loop_indices(graph.size(), known_inliers)
    kept = loops[weights[loops] >= 0.5]
    if len(kept) < MIN_LOOPS_FOR_SCALE:
        return 1.0
    factors = [graph.at(int(i)) for i in kept]
    whitened = [2.0 * factor.error(values) / chi2.median(factor.dim()) for factor in factors]
    return float(np.median(whitened))


def readmitted(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights: np.ndarray, known_inliers: list[int]
) -> np.ndarray:
    """`weights` with weight 1 for every loop whose squared whitened error at `values` lies within
    `READMIT_SIGMAS` robust standard deviations (1.4826 x median absolute deviation, in log10) above the
    median of the kept loops'; the others keep their weight.

    A threshold at a chi-square quantile of the estimated scale cuts real loops when their errors are
    heavy-tailed; in log space that tail stays within a few robust sigmas of the kept loops' median, and wrong
    loops lie far beyond it.
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


def _scaled_run_wins(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    scaled_values: gtsam.Values,
    scaled_weights: np.ndarray,
    known_inliers: list[int],
) -> bool:
    """Whether the scaled run's result replaces the first run's. It must keep more than `MIN_KEPT_SHARE` of
    the loops the first run kept: what it is for is the few outliers that loose covariances let pass, and a
    threshold that rejects many of the first run's loops cuts their own heavy tail, or real loops with a small
    shared bias. And the loops both runs kept must fit at least `MIN_FIT_GAIN` times better (median squared
    error) without the ones it dropped: those were bending the graph, not just the tail of the real loops.
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


def _gnc(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    known_inliers: list[int],
    config: GraphConfig,
    threshold: float | None = None,
) -> tuple[gtsam.Values, np.ndarray]:
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
