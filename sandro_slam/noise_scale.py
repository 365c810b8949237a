"""How much to trust the odometry against the loops, estimated from the data: variance component estimation.

The odometry factors' covariances come from a model (`graph.odometry_*`) that cannot know how good a given odometry
is: a LiDAR-inertial front end may drift by 0.01 % of the distance or by 1 %. Once the robust back end has decided
which loops to keep, the odometry's covariances are scaled until both groups, odometry and loops, fit as well as
their covariances say: each group's squared whitened residuals over its redundancy (the degrees of freedom it
contributes, from the marginal covariances) are equal (Foerstner's variance component estimation). The scale only
tightens the odometry (at most 1): a model looser than the configured one lets loops bend the graph where none
constrain it.
"""

from __future__ import annotations

import gtsam
import numpy as np

from sandro_slam.factors import scaled_noise
from sandro_slam.variance_components import group_fits

MIN_LOOPS = 10  # kept loops needed to estimate the scale
MAX_ITERATIONS = 30
TOLERANCE = 0.02  # stop when the scale changes by less than this share
MIN_SCALE = 1e-6
REFINE_RELATIVE_TOL = 1e-10


def rescale_odometry(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, odometry: list[int], loops: list[int]
) -> tuple[gtsam.Values, float]:
    """The values of `graph` restricted to its other factors (priors) and the factors at `odometry` and `loops`
    (the kept ones), optimised with the odometry covariances scaled by the estimated factor; and that factor
    (1: unchanged, also with fewer than `MIN_LOOPS` loops)."""
    if len(loops) < MIN_LOOPS:
        return values, 1.0
    chosen = set(odometry) | set(loops)
    others = [i for i in range(graph.size()) if i not in chosen and not _is_between(graph.at(i))]
    scale = 1.0
    for _ in range(MAX_ITERATIONS):
        scaled = gtsam.NonlinearFactorGraph()
        for i in others + loops:
            scaled.add(graph.at(i))
        for i in odometry:
            scaled.add(scaled_noise(graph.at(i), scale))
        values = _optimized(scaled, values)
        groups = [None] * len(others) + ["loops"] * len(loops) + ["odometry"] * len(odometry)
        fit = group_fits(scaled, values, groups)
        loop_fit, odometry_fit = (fit[g][0] / max(fit[g][1], 1e-12) for g in ("loops", "odometry"))
        # The odometry's factor moves by the ratio squared: the plain ratio approaches it only slowly when the
        # model is far off.
        target = float(np.clip(scale * (odometry_fit / loop_fit) ** 2, MIN_SCALE, 1.0))
        converged = abs(target / scale - 1.0) < TOLERANCE
        if target == scale or converged:
            break
        scale = target
    return values, scale


def _optimized(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Values:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(REFINE_RELATIVE_TOL)
    params.setAbsoluteErrorTol(0.0)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def _is_between(factor: gtsam.NonlinearFactor) -> bool:
    return isinstance(factor, gtsam.BetweenFactorPose3)
