"""The robust back end: which loop factors of a pose graph to keep, under a truncated least squares (TLS) cost.

The prior and odometry factors are known inliers; every other factor is a loop the back end may reject. TLS keeps a
loop exactly when its whitened error lies below the inlier threshold at the solution. It is reached from the loops
that agree with their neighbours (`loop_consistency`): solved with those (from their chordal relaxation, `chordal`,
not from the initial values), every loop is judged at the solution, and solving and judging alternate until the
kept loops no longer change; each round is one least-squares solve. Where too few loops have neighbours to agree
with, graduated non-convexity (gtsam GNC) finds the TLS solution from the start instead, as it does for the
Geman-McClure cost. When the solution bends the odometry beyond its covariances, TLS is also judged from the
initial values (the odometry) and the solution of lower TLS cost stands: loops aliased by a repeated structure
agree with each other, and can be grown into such a solution. Last, a loop whose removal would lower the cost of
the rest beyond chance goes: a wrong loop can bend poses that long odometry holds loosely until its own error is
small. Where the seed loops fit far worse than their covariances say, every threshold grows with them. All of it
runs on the graph with its plain odometry runs condensed (`chain_reduction`: poses that only odometry holds are
not solved for while loops are decided); the whole graph is solved once at the end. See docs/back-end.md for the
measurements behind the settings below.
"""

from __future__ import annotations

import functools

import gtsam
import numpy as np
from scipy.stats import chi2

from sandro_slam.chain_reduction import condensed
from sandro_slam.chordal import chordal_values
from sandro_slam.config import GraphConfig
from sandro_slam.covariance import FactorCovariances
from sandro_slam.loop_consistency import supported_loops

GNC_LM_ITERATIONS = 5  # LM iterations per GNC step (gtsam: 100): each step starts from the last
GNC_LM_RELATIVE_TOL = 1e-3  # LM relative cost decrease that ends a GNC step (gtsam: 1e-5)
GNC_WEIGHTS_TOL = 0.0  # TLS: never end early because every weight is within this of 0 or 1 (gtsam: 1e-4). A wrong
# loop with a tight covariance makes GNC's first control parameter tiny, which leaves every real loop's weight
# near 0 at the start: that must not pass for converged
GNC_MU_STEP = {"gnc_tls": 2.0, "gnc_gm": 1.4}  # factor on GNC's control parameter per step (gtsam: 1.4)
SEED_RELATIVE_TOL = 1e-5  # of the solves between TLS rounds, which start near their solution (gtsam's default)
MAX_LM_ITERATIONS = 500  # per LM solve (gtsam: 100)
REFINE_RELATIVE_TOL = 1e-10  # of the final LM on the kept factors: on graphs with loose covariances poses move
# metres for a relative cost change of gtsam's default 1e-5
MIN_LOOPS_FOR_SCALE = 10  # kept loops needed to estimate their variance factor
MIN_KEPT_SHARE = 0.8  # noise_scale 'estimated': of the first run's loops, the scaled run must keep more than this
MIN_FIT_GAIN = 2.0  # and fit those it keeps this much better (median squared error) than the first run
MIN_TIGHT_FACTOR = 2.0  # noise_scale 'estimated': the seed loops' variance factor above which the covariances are
# taken as too tight, and every inlier threshold grows by it (`_seed_scales`; below it they stand as given)
MIN_SEED_LOOPS = 10  # loops agreeing with their neighbours needed to start TLS from them rather than run GNC
ADMISSION_FACTOR = 2.0  # on the inlier threshold, of the innovation tests against the seed solution and the one
# grown from it: the poses where the seed loops are sparse are still away from where all loops put them
ADMISSION_INFORMATION_FLOOR = 1e-8  # x the median information diagonal, on every pose, where the seed graph's
# information matrix is numerically not positive definite (SE-Sync's cubicle: roll and pitch sigmas of 1e3 rad)
ADMISSION_ROUNDS = 2  # innovation tests, each followed by TLS from the loops it admits
MAX_TLS_ROUNDS = 10  # solve-and-judge rounds (they end when the kept loops no longer change)
SCALED_TLS_ROUNDS = 2  # of the scaled run: at the tighter thresholds each round peels more of the real loops'
# heavy tail, which the readmission then restores; outliers the first run let pass go in the first round
MAX_REMOVAL_ROUNDS = 10  # removal tests after the growth, each followed by TLS without the loops it removes; a
# bound only: they end when no kept loop exceeds both bounds of the test (SE-Sync's ais2klinik takes 6)
REMOVAL_SIGMAS = 3.0  # a loop is removed only when its removal cost drop also lies this many robust standard
# deviations (in log10) above the kept loops' median drop: real loops of graphs whose errors are heavy-tailed
# exceed the chi-square bound, but not their own distribution (a chi-square's lie within 2.7-3.0 to 1e-5)
REMOVAL_SHARE = 0.5  # a loop over its bound is removed in a round when its excess (removal cost drop over the
# bound, less 1) is at least this share of the round's largest: a wrong loop bends the graph under the real
# loops near it, and their excess falls once it is gone
READMIT_SIGMAS = 7.0  # noise_scale 'estimated': a rejected loop comes back when its log squared error is within
# this many robust standard deviations of the kept loops'


def robust_optimize(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int], config: GraphConfig
) -> tuple[gtsam.Values, np.ndarray]:
    """Optimise `graph` with the configured robust back end; returns the values and a weight per factor
    (1 for known inliers; below 0.5 means rejected).

    The inlier threshold of a loop is its squared whitened error at `inlier_probability` of the chi-square of
    its dimension. gnc_tls: TLS from the loops that agree with their neighbours (`supported_loops`), when at
    least `MIN_SEED_LOOPS` of them fit together (`_seeded`), grown by the innovation test (`_grown`); else
    gtsam's GncLMOptimizer from `initial` with `known_inliers` (prior and odometry factor indices) never
    down-weighted (`_gnc`). When that solution strains the known inliers (`_strained`), TLS is also judged from
    `initial` (`_truncated`) and the solution of lower TLS cost stands (`_lower_cost`). Grown from seeds, the
    loops whose removal would lower the others' cost beyond chance go (`_pruned`). gnc_gm: always
    GncLMOptimizer with the Geman-McClure cost. Then Levenberg-Marquardt to convergence (`REFINE_RELATIVE_TOL`)
    on the factors kept.
    With `noise_scale: estimated`, for graphs whose covariances are not to scale: when the seed loops fit far worse
    than their covariances say, every threshold grows by how much (`_seed_scales`); when the loops the first run
    kept fit better than their covariances say (`variance_factor` below 1), a second run takes the thresholds
    times that factor (TLS from the first run's loops, or GNC from `initial`), loops it rejected that fit as
    well as the heavy tail of those it kept come back, beyond the first run's thresholds only where their
    innovation is within them (`readmitted`), and its result replaces the first when it keeps more than
    `MIN_KEPT_SHARE` of the loops the first kept and fits them clearly better, or keeps more loops than the
    first, those it adds within their thresholds (`_scaled_run_wins`). Graphs whose loops differ in dimension
    keep the first run.
    none: plain Levenberg-Marquardt, every weight 1.
    The loops are decided on the graph with its runs of plain poses condensed (`chain_reduction.condensed`; the
    seeds are found on the whole graph, where the odometry's steps count the neighbourhood), and the whole graph is
    then solved with the factors kept, from the condensed solution.
    """
    if config.robust == "none":
        return gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize(), np.ones(graph.size())
    loops = _loop_indices(graph.size(), known_inliers)
    if not len(loops):
        return refined(graph, initial, np.ones(graph.size())), np.ones(graph.size())
    seed = loops[supported_loops(graph, known_inliers)] if config.robust == "gnc_tls" else loops[:0]
    reduced = condensed(graph, initial, known_inliers)
    if reduced is None:
        return _decided(graph, initial, known_inliers, config, seed)
    position = {int(index): n for n, index in enumerate(reduced.original)}
    reduced_seed = np.array([position[int(index)] for index in seed], dtype=int)
    values, weights = _decided(
        reduced.graph, reduced.initial, reduced.known_inliers, config, reduced_seed, reduced.hidden_dims
    )
    whole = reduced.weights_of_whole(weights, graph.size())
    return refined(graph, reduced.values_of_whole(values), whole), whole


def _decided(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    known_inliers: list[int],
    config: GraphConfig,
    seed: np.ndarray,
    hidden_dims: int = 0,
) -> tuple[gtsam.Values, np.ndarray]:
    """`robust_optimize` from its `seed` loops on, on `graph` or on its condensed form (`chain_reduction`), whose
    condensing removed `hidden_dims` measurement dimensions and as many unknowns."""
    loops = _loop_indices(graph.size(), known_inliers)
    dims = np.array([graph.at(int(i)).dim() for i in loops])
    thresholds = chi2.ppf(config.inlier_probability, dims)
    seeded = _seeded(graph, initial, known_inliers, seed, thresholds)
    tight = 1.0
    if seeded is not None:
        scales = (1.0, 1.0)  # of the loops' and the poses' covariances in the innovation test
        if config.noise_scale == "estimated":
            ratio, loop_scale, pose_scale = _seed_scales(graph, *seeded, known_inliers, hidden_dims)
            if ratio > MIN_TIGHT_FACTOR:  # covariances too tight: every threshold grows
                tight = loop_scale
                thresholds = thresholds * tight
            scales = (min(1.0, loop_scale), min(1.0, pose_scale))  # covariances not to scale admit no more
        covariances = _Covariances(graph)
        values, weights = _grown(graph, *seeded, known_inliers, thresholds, scales, covariances)
    else:
        values, weights = _gnc(graph, initial, known_inliers, config, 0.5 * thresholds[0])
    if config.robust == "gnc_tls" and _strained(graph, values, known_inliers, tight, hidden_dims):
        judged = _truncated(graph, initial, np.ones(graph.size()), known_inliers, thresholds)
        values, weights = _lower_cost(graph, (values, weights), judged, known_inliers, thresholds)
    if seeded is not None:
        values, weights = _pruned(
            graph, values, weights, known_inliers, thresholds, config.inlier_probability, tight, covariances
        )
    values = refined(graph, values, weights)
    if config.noise_scale == "estimated" and len(set(dims)) == 1:
        scale = variance_factor(graph, values, weights, known_inliers)
        if scale < 1.0:  # 1: too few loops to tell; above 1 the stated covariances are not too loose
            if seeded is not None:  # TLS at the tighter thresholds from the first run's loops
                scaled = _truncated(graph, values, weights, known_inliers, thresholds * scale, SCALED_TLS_ROUNDS)
            else:
                scaled = _gnc(graph, initial, known_inliers, config, 0.5 * thresholds[0] * scale)
            scaled_weights = readmitted(graph, *scaled, known_inliers, thresholds)
            if not np.array_equal(scaled_weights, weights):  # the same loops: the first run's solution
                scaled = refined(graph, scaled[0], scaled_weights), scaled_weights
                if _scaled_run_wins(graph, values, weights, *scaled, known_inliers, thresholds):
                    values, weights = scaled
    return values, weights


def _grown(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray,
    scales: tuple[float, float],
    covariances: _Covariances | None = None,
) -> tuple[gtsam.Values, np.ndarray]:
    """TLS at the squared whitened error `thresholds` (per loop) grown from the seed solution (`values`,
    `weights`): the loops outside it that fit it as far as it is known (`_admitted`, within `ADMISSION_FACTOR`
    times their thresholds, with the loops' and the poses' covariances `scales` times as large in every round:
    the seed solution's, not those of a solution that the loops admitted in between bend) join, TLS among those
    (`_truncated`), and again from that solution, `ADMISSION_ROUNDS` times or until nothing is admitted.
    `covariances` computes the poses' covariances (and keeps the last for the removal test)."""
    covariances = covariances or _Covariances(graph)
    for _ in range(ADMISSION_ROUNDS):
        values, candidates = _admitted(
            graph, values, weights, known_inliers, thresholds * ADMISSION_FACTOR, scales, covariances
        )
        if np.array_equal(candidates, weights):
            break
        values, weights = _truncated(graph, values, candidates, known_inliers, thresholds)
    return values, weights


def _pruned(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray,
    probability: float,
    scale: float = 1.0,
    covariances: _Covariances | None = None,
) -> tuple[gtsam.Values, np.ndarray]:
    """The removal test on the kept loops of the solution (`values`, `weights`), with the covariances taken
    `scale` times as large.

    Where the poses are held loosely (long odometry, few loops), a wrong loop bends them until its own error is
    far below its threshold, and TLS judged on errors keeps it. What it costs the rest shows in the cost drop of
    removing it, r^T (I - M)^-1 r, r its whitened error and M = A Sigma A^T its whitened Jacobian A through the
    covariance Sigma of its poses at the solution (exact for the linearised graph): for a real loop that is its
    innovation against all other factors, chi-square distributed. A loop is removed when its drop exceeds the
    chi-square quantile at `probability` for the whole set of kept loops (1 - (1 - probability) / their number:
    at the per-loop quantile, TLS's threshold, one real loop in a hundred would go), and the tail of the kept
    loops' drops (`REMOVAL_SIGMAS`: real loops of graphs with heavy-tailed errors exceed the first). Of those,
    the ones within `REMOVAL_SHARE` of the largest excess go for good, TLS among the other loops of `weights`
    (`_truncated`, at `thresholds`) is solved again, up to `MAX_REMOVAL_ROUNDS` times. `covariances` computes the
    poses' covariances (the growth's last, where it ended at `values`)."""
    covariances = covariances or _Covariances(graph)
    loops = _loop_indices(graph.size(), known_inliers)
    dims = np.array([graph.at(int(i)).dim() for i in loops])
    candidates = weights.copy()
    for _ in range(MAX_REMOVAL_ROUNDS):
        mine = weights[loops] >= 0.5
        if mine.sum() < MIN_LOOPS_FOR_SCALE:  # too few drops for their tail
            break
        try:
            at_solution = covariances(weights, values)
        except ValueError:
            break
        drops = np.zeros(len(loops))
        drops[mine] = at_solution.mahalanobis([graph.at(int(i)) for i in loops[mine]], values, 1.0, -1.0)
        limits = scale * chi2.isf((1.0 - probability) / mine.sum(), dims)
        excess = np.where(drops > _tail_limit(drops[mine], REMOVAL_SIGMAS), drops / limits - 1.0, 0.0)
        if excess.max() <= 0.0:
            break
        candidates[loops[(excess > 0.0) & (excess >= REMOVAL_SHARE * excess.max())]] = 0.0
        values = refined(graph, values, candidates, relative_tol=SEED_RELATIVE_TOL)
        values, weights = _truncated(graph, values, candidates, known_inliers, thresholds)
    return values, weights


def _dimensions(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> tuple[int, int]:
    """(measurement dimensions of `graph`'s factors, their redundancy: those less the unknowns of `values`)."""
    measured = sum(graph.at(i).dim() for i in range(graph.size()))
    return measured, measured - values.dim()


def _strained(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    known_inliers: list[int],
    scale: float = 1.0,
    hidden_dims: int = 0,
) -> bool:
    """Whether the known inliers (prior, odometry) fit `values` worse than their covariances (times `scale`) say:
    their squared whitened errors sum to more than `scale` times their dimensions (with `hidden_dims`, those of
    the odometry steps a condensed graph folded into its runs' factors). At a least-squares optimum they sum to less
    (the fit absorbs part of their noise); above it, the loops kept bend the odometry."""
    squared = sum(2.0 * graph.at(i).error(values) for i in known_inliers)
    return squared > scale * (sum(graph.at(i).dim() for i in known_inliers) + hidden_dims)


def _lower_cost(
    graph: gtsam.NonlinearFactorGraph,
    first: tuple[gtsam.Values, np.ndarray],
    second: tuple[gtsam.Values, np.ndarray],
    known_inliers: list[int],
    thresholds: np.ndarray,
) -> tuple[gtsam.Values, np.ndarray]:
    """Of two (values, weights) solutions, the one of lower TLS cost (`tls_cost`)."""
    lower = tls_cost(graph, second[0], known_inliers, thresholds) < tls_cost(graph, first[0], known_inliers, thresholds)
    return second if lower else first


def tls_cost(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, known_inliers: list[int], thresholds: np.ndarray
) -> float:
    """The truncated least squares cost of `graph` at `values`: the known inliers' squared whitened errors plus
    every loop's, truncated at its threshold (`thresholds`, per loop, in the order of `_loop_indices`)."""
    squared = np.array([2.0 * graph.at(int(i)).error(values) for i in _loop_indices(graph.size(), known_inliers)])
    known = sum(2.0 * graph.at(i).error(values) for i in known_inliers)
    return known + float(np.minimum(squared, thresholds).sum())


def _seeded(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    known_inliers: list[int],
    seed: np.ndarray,
    thresholds: np.ndarray,
) -> tuple[gtsam.Values, np.ndarray] | None:
    """The solution with the known inliers and the `seed` loops (those that agree with their neighbours), and its
    weights, once the seed loops fit it together: none beyond its threshold and beyond the seed loops' own tail
    (`READMIT_SIGMAS` robust standard deviations of their log errors). Those that do not are dropped and the rest
    solved again, once. None when fewer than `MIN_SEED_LOOPS` remain or they still do not fit: GNC then decides."""
    loops = _loop_indices(graph.size(), known_inliers)
    threshold_of = dict(zip(loops.tolist(), thresholds))
    for _ in range(2):
        if len(seed) < MIN_SEED_LOOPS:
            return None
        weights = np.ones(graph.size())
        weights[loops] = 0.0
        weights[seed] = 1.0
        values = _solved_from_scratch(graph, initial, weights)
        errors = np.array([2.0 * graph.at(int(i)).error(values) for i in seed])
        misfit = (errors > np.array([threshold_of[int(i)] for i in seed])) & (errors > _tail_limit(errors))
        if not misfit.any():
            return values, weights
        seed = seed[~misfit]
    return None


def _solved_from_scratch(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, weights: np.ndarray) -> gtsam.Values:
    """LM to convergence on the factors of weight >= 0.5, started from their chordal relaxation (`chordal_values`)
    rather than `initial`: from composed odometry LM can stop in a local minimum or creep for hundreds of
    iterations. `initial` is the start when the relaxation does not apply or its solution costs more than
    `initial` already does (then the lower of the two solutions)."""
    kept = _kept(graph, weights)
    start = chordal_values(kept, initial)
    if start is None:
        return refined(graph, initial, weights)
    rest = gtsam.Values(initial)  # poses the kept factors do not touch stay where they were
    for key in start.keys():
        rest.erase(key)
    start.insert(rest)
    values = refined(graph, start, weights)
    if kept.error(values) <= kept.error(initial):
        return values
    other = refined(graph, initial, weights)
    return values if kept.error(values) <= kept.error(other) else other


def _admitted(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray,
    scales: tuple[float, float],
    covariances: _Covariances,
) -> tuple[gtsam.Values, np.ndarray]:
    """The seed solution with the loops outside the seed that pass the innovation test against it, solved again.

    A loop far from the seed loops meets a solution that only the odometry holds there: its plain error can be
    large while the poses' uncertainty says it is plausible. The test whitens the loop's error by its covariance
    plus its poses' covariance at `values` (the seed solution, or one grown from it) and admits it within its
    threshold. The loop's covariance is taken `scales[0]` times, the poses' `scales[1]` times as large
    (at most 1, so covariances not to scale admit no more). The poses' covariance is their joint one, with
    their cross-covariance: far from the graph's priors each pose alone is uncertain while the two move together,
    and taken as uncorrelated their marginals let loops in that contradict the odometry between them (SE-Sync's
    ais2klinik at 30 % outliers: 18 injected loops admitted, none with the joint covariance; `_innovation_within`).
    A loop within its threshold by its own covariance alone passes without them (the poses' covariance only
    lowers the innovation). What the test lets in, `_truncated` judges again.
    Returns the solution and the weights of the seed and admitted loops (1), the candidates of `_truncated`."""
    loops = _loop_indices(graph.size(), known_inliers)
    outside = weights[loops] < 0.5
    if not outside.any():
        return values, weights
    at_solution = _floored(covariances, weights, values)
    if at_solution is None:  # poses that only loops outside the seed hold: no covariance to test against
        return values, weights
    indices, limits = loops[outside], thresholds[outside]
    factors = [graph.at(int(i)) for i in indices]
    # within the limit by its own covariance alone: the poses' covariance only lowers the innovation
    plain = np.array([2.0 * factor.error(values) for factor in factors]) <= scales[0] * limits
    tested = np.flatnonzero(~plain)
    passed = _innovation_within(at_solution, [factors[n] for n in tested], values, limits[tested], scales)
    admitted = weights.copy()
    admitted[indices[plain]] = 1.0
    admitted[indices[tested[passed]]] = 1.0
    if np.array_equal(admitted, weights):
        return values, weights
    return refined(graph, values, admitted, relative_tol=SEED_RELATIVE_TOL), admitted


def _seed_scales(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    known_inliers: list[int],
    hidden_dims: int = 0,
) -> tuple[float, float, float]:
    """How the seed solution (`values`, `weights`) fits against its covariances: (the seed loops'
    `variance_factor`; that over the mean share of a factor's error a least-squares fit leaves (redundancy over
    measurement dimensions: the fit pulls every factor's error below its noise), how many times the loops'
    covariances understate (above 1) or overstate their noise; the seed solution's a-posteriori variance factor
    (2 cost / redundancy), the same for the poses'). The median, not the cost, for the loops: a wrong seed inflates
    the cost. Without redundancy the fit says nothing of the noise: both scales 1. `hidden_dims`: the measurement
    dimensions (and unknowns) a condensed graph folded away, counted as in the whole graph."""
    ratio = variance_factor(graph, values, weights, known_inliers)
    kept = _kept(graph, weights)
    measured, redundancy = _dimensions(kept, values)
    if redundancy <= 0:
        return ratio, 1.0, 1.0
    return ratio, ratio * (measured + hidden_dims) / redundancy, 2.0 * kept.error(values) / redundancy


def _chi2_ratio(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> float:
    """The factor's squared whitened error at `values` over the chi-square median of its dimension."""
    return 2.0 * factor.error(values) / _chi2_median(factor.dim())


@functools.cache
def _chi2_median(dim: int) -> float:
    return float(chi2.median(dim))


def _tail_limit(errors: np.ndarray, sigmas: float = READMIT_SIGMAS) -> float:
    """The largest squared whitened error within `sigmas` robust standard deviations (1.4826 x median absolute
    deviation, in log10) above the median of `errors`."""
    log_error = np.log10(np.maximum(errors, 1e-300))
    median = np.median(log_error)
    sigma = 1.4826 * np.median(np.abs(log_error - median))
    return float(10.0 ** (median + sigmas * sigma))


def _truncated(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    candidates: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray,
    max_rounds: int = MAX_TLS_ROUNDS,
) -> tuple[gtsam.Values, np.ndarray]:
    """TLS among the `candidates` (weight 1) from `values`: keep those whose squared whitened error is within
    their `thresholds` (per loop, in the order of `_loop_indices`), solve with them, judge the candidates again,
    until the kept loops no longer change or after `max_rounds` solves. Returns the solution and its 0/1
    weights."""
    loops = _loop_indices(graph.size(), known_inliers)
    mine = candidates[loops] >= 0.5
    weights = candidates.copy()
    for _ in range(max_rounds):
        errors = np.array([2.0 * graph.at(int(i)).error(values) for i in loops])
        judged = weights.copy()
        judged[loops] = ((errors <= thresholds) & mine).astype(float)
        if np.array_equal(judged, weights):
            break
        weights = judged
        values = refined(graph, values, weights, relative_tol=SEED_RELATIVE_TOL)
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


def refined(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    relative_tol: float = REFINE_RELATIVE_TOL,
) -> gtsam.Values:
    """Levenberg-Marquardt to convergence (`relative_tol`) on the factors of weight >= 0.5."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(MAX_LM_ITERATIONS)
    return gtsam.LevenbergMarquardtOptimizer(_kept(graph, weights), values, params).optimize()


def _kept(graph: gtsam.NonlinearFactorGraph, weights: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """The factors of `graph` of weight >= 0.5."""
    kept = gtsam.NonlinearFactorGraph()
    for index in np.flatnonzero(weights >= 0.5):
        kept.add(graph.at(int(index)))
    return kept


class _Covariances:
    """`FactorCovariances` of the factors of `graph` kept by some weights at some values, remembering the last: the
    removal test (`_pruned`) starts at the solution where the growth's last innovation test (`_admitted`) admitted
    nothing, and need not factorise the same information matrix again."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph):
        self._graph = graph
        self._last: tuple[np.ndarray, gtsam.Values, float, FactorCovariances] | None = None

    def __call__(self, weights: np.ndarray, values: gtsam.Values, floor: float = 0.0) -> FactorCovariances:
        """The covariances of the factors of weight >= 0.5 at `values` (the same object as the last call's to
        reuse it), with `floor` as in `FactorCovariances`.

        Raises:
            ValueError: as `FactorCovariances`.
        """
        kept = weights >= 0.5
        if self._last is not None:
            last_kept, last_values, last_floor, covariances = self._last
            if last_values is values and last_floor == floor and np.array_equal(last_kept, kept):
                return covariances
        covariances = FactorCovariances(_kept(self._graph, weights), values, floor=floor)
        self._last = kept, values, floor, covariances
        return covariances


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
    return float(np.median([_chi2_ratio(graph.at(int(i)), values) for i in kept]))


def readmitted(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray | None = None,
) -> np.ndarray:
    """`weights` with weight 1 for every loop whose squared whitened error at `values` lies within
    `READMIT_SIGMAS` robust standard deviations (1.4826 x median absolute deviation, in log10) above the
    median of the kept loops'; the others keep their weight. With `thresholds` (per loop, in the order of
    `_loop_indices`), a loop beyond its threshold at `values` comes back only when its innovation is within it
    (`_innovation_within`): to first order, TLS solved with it would keep it.

    A threshold at a chi-square quantile of the estimated scale cuts real loops when their errors are
    heavy-tailed; in log space that tail stays within a few robust sigmas of the kept loops' median, and wrong
    loops lie far beyond it. Where the kept loops' errors spread over decades that tail takes in nearly every
    loop (SE-Sync's sphere_bignoise with its covariances rescaled to its noise: every injected loop, and solving
    with them took minutes); of those beyond their thresholds the innovation keeps the real ones apart.
    """
    loops = _loop_indices(graph.size(), known_inliers)
    errors = np.array([2.0 * graph.at(int(i)).error(values) for i in loops])
    kept = weights[loops] >= 0.5
    if kept.sum() < MIN_LOOPS_FOR_SCALE:
        return weights
    within = errors <= _tail_limit(errors[kept])
    if thresholds is not None:
        beyond = np.flatnonzero(within & ~kept & (errors > thresholds))
        within[beyond] = False
        at_solution = _floored(_Covariances(graph), weights, values) if len(beyond) else None
        if at_solution is not None:
            factors = [graph.at(int(i)) for i in loops[beyond]]
            within[beyond[_innovation_within(at_solution, factors, values, thresholds[beyond])]] = True
    out = weights.copy()
    out[loops[within]] = 1.0
    return out


def _floored(covariances: _Covariances, weights: np.ndarray, values: gtsam.Values) -> FactorCovariances | None:
    """The covariances of the factors of weight >= 0.5 at `values`; where they leave directions free (roll and
    pitch of planar odometry, chains held by weak priors), bounded by a weak prior on every pose
    (`ADMISSION_INFORMATION_FLOOR`); None where even then a pose is free."""
    for floor in (0.0, ADMISSION_INFORMATION_FLOOR):
        try:
            return covariances(weights, values, floor=floor)
        except ValueError:
            continue
    return None


def _innovation_within(
    at_solution: FactorCovariances,
    factors: list[gtsam.NonlinearFactor],
    values: gtsam.Values,
    limits: np.ndarray,
    scales: tuple[float, float] = (1.0, 1.0),
) -> np.ndarray:
    """(len(factors),) bool: whether each factor's squared whitened innovation at `values` lies within its limit:
    its error whitened by its covariance (`scales[0]` times) plus its poses' joint covariance of `at_solution`
    (`scales[1]` times; `FactorCovariances.mahalanobis`): to first order, what solving with it adds to the least
    squares cost, which TLS pays rather than the limit. The joint covariance, from solves, is taken only where
    the poses' marginals alone pass: the others it would refuse too (on the SE-Sync graphs the joint covariance
    gives the larger innovation for 98-99.9 % of the loops)."""
    within = at_solution.mahalanobis(factors, values, *scales, correlated=False) <= limits
    undecided = np.flatnonzero(within)
    within[undecided] = at_solution.mahalanobis([factors[n] for n in undecided], values, *scales) <= limits[undecided]
    return within


def _scaled_run_wins(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    scaled_values: gtsam.Values,
    scaled_weights: np.ndarray,
    known_inliers: list[int],
    thresholds: np.ndarray,
) -> bool:
    """Whether the scaled run's result replaces the first run's. It must keep more than `MIN_KEPT_SHARE` of
    the loops the first run kept: what it is for is the few outliers that loose covariances let pass, and a
    threshold that rejects many of the first run's loops cuts their own heavy tail, or real loops with a small
    shared bias. And the loops both runs kept must fit at least `MIN_FIT_GAIN` times better (median squared
    error) without the ones it dropped: those were bending the graph, not just the tail of the real loops.
    A result that keeps more loops than the first run wins as well when each loop it adds lies within its threshold
    (of `thresholds`, per loop) at its solution: TLS would keep them there. Where it keeps every loop the first
    run kept, those it adds fit like the kept loops (`readmitted`), and the first run's innovation test, whose
    covariances come from the seed loops' fit, turned them away as the heavy tail of the real loops' errors.
    Where it keeps others in place of some, the first run ended in another minimum: at tighter thresholds more
    loops fit (GNC from the initial values, on a graph of exact loops a third of whose loops are wrong).
    """
    loops = _loop_indices(len(weights), known_inliers)
    kept = loops[weights[loops] >= 0.5]
    both = kept[scaled_weights[kept] >= 0.5]
    added = (scaled_weights[loops] >= 0.5) & (weights[loops] < 0.5)
    dropped = len(kept) - len(both)
    if dropped == 0 or added.sum() > dropped:
        errors = np.array([2.0 * graph.at(int(i)).error(scaled_values) for i in loops[added]])
        return bool(added.any() and (errors <= thresholds[added]).all())
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
