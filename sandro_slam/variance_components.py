"""Variance components: how far each group of a graph's factors over- or understates its noise, estimated from the
residuals at the least-squares solution (Förstner's iteration), and the graph reweighted with them.

A group's variance factor is the sum of its factors' squared whitened errors over their redundancy: each factor's
dimension less the trace of A Sigma A^T (A its whitened Jacobian, Sigma the solution's covariance of its
variables), the part of its error the rest of the graph can check. Each group's covariances are scaled by its
variance factor and the graph solved again, until the variance factors settle.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import gtsam
import numpy as np

from sandro_slam.covariance import FactorCovariances
from sandro_slam.factors import scaled_noise
from sandro_slam.robust_backend import refined

MAX_ROUNDS = 5
SETTLED = 0.1  # rounds end when no group's factor changes by more than this share
MIN_REDUNDANCY = 5.0  # a group seen by less takes the median factor of the others


def reweighted(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    weights: np.ndarray,
    groups: Sequence[Hashable | None],
    reference: Hashable,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[Hashable, float]]:
    """`graph` with every BetweenFactorPose3's covariance times its group's variance factor, the solution of its
    factors of weight >= 0.5 from `values` (theirs at unit factors), and the factors. `groups[i]`: factor i's
    group, None to keep it as it is (priors). The factors are relative to group `reference`'s, which keeps its
    covariances; only the kept factors count.

    Raises:
        ValueError: `groups` does not match the graph, or no kept factor is of group `reference`.
    """
    if len(groups) != graph.size():
        raise ValueError(f"{len(groups)} groups for {graph.size()} factors")
    kept = np.flatnonzero(weights >= 0.5)
    scales = {groups[i]: 1.0 for i in kept if groups[i] is not None}
    if reference not in scales:
        raise ValueError(f"the reference group {reference!r} has no kept factor")
    kept_groups = [groups[i] for i in kept]
    scaled = _scaled(graph, groups, scales, kept)
    for _ in range(MAX_ROUNDS):
        factors = _estimated(scaled, kept_groups, scales, values, reference)
        settled = all(abs(factors[g] / scales[g] - 1.0) <= SETTLED for g in scales)
        scales = factors
        scaled = _scaled(graph, groups, scales, kept)
        values = refined(scaled, values, np.ones(len(kept)))
        if settled:
            break
    every = {g: scales.get(g, 1.0) for g in groups if g is not None}
    return _scaled(graph, groups, every, np.arange(graph.size())), values, scales


def group_fits(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, groups: Sequence[Hashable | None]
) -> dict[Hashable, tuple[float, float]]:
    """Per group of `graph`'s factors (`groups[i]`: factor i's, None: not counted), at `values` (a solution of
    `graph`): the sum of their squared whitened errors and their redundancy, the sum of dim - tr(A Sigma A^T)."""
    covariances = FactorCovariances(graph, values)
    out: dict[Hashable, tuple[float, float]] = {}
    for index, group in enumerate(groups):
        if group is not None:
            b, M = covariances.projected(graph.at(index), values)
            squares, redundancy = out.get(group, (0.0, 0.0))
            out[group] = (squares + float(b @ b), redundancy + len(b) - float(np.trace(M)))
    return out


def _estimated(
    scaled: gtsam.NonlinearFactorGraph,
    groups: Sequence[Hashable | None],
    scales: dict[Hashable, float],
    values: gtsam.Values,
    reference: Hashable,
) -> dict[Hashable, float]:
    """The groups' factors, relative to `reference`'s, from the residuals at `values` of the graph scaled by
    `scales` (`scaled`)."""
    seen = {
        g: scales[g] * squares / redundancy
        for g, (squares, redundancy) in group_fits(scaled, values, groups).items()
        if redundancy >= MIN_REDUNDANCY
    }
    fallback = float(np.median(list(seen.values()))) if seen else 1.0
    factors = {g: seen.get(g, fallback) for g in scales}
    return {g: factor / factors[reference] for g, factor in factors.items()}


def _scaled(
    graph: gtsam.NonlinearFactorGraph,
    groups: Sequence[Hashable | None],
    scales: dict[Hashable, float],
    indices: np.ndarray,
) -> gtsam.NonlinearFactorGraph:
    """The factors `indices` of `graph`, each with its covariance times its group's scale."""
    out = gtsam.NonlinearFactorGraph()
    for index in indices:
        factor, group = graph.at(int(index)), groups[index]
        out.add(factor if group is None or scales[group] == 1.0 else scaled_noise(factor, scales[group]))
    return out
