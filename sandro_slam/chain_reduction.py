"""A pose graph with its plain odometry chains condensed: where the robust back end decides, poses that only odometry
holds need not be solved for.

A pose is plain when exactly two factors touch it, both odometry (known-inlier Gaussian between factors) to two
other poses. Each run of plain poses between two others is replaced by one between factor: the composition of its
measurements, with their covariances carried along it to first order (right perturbations: a step's covariance
moved through the adjoint of the rest of the run). For a linear graph this is exact: eliminating a chain's inner
poses leaves the same marginals and the same optimum on every other pose. After the decision the whole graph is
solved from the condensed solution, each run's poses composed from its start.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import gtsam
import numpy as np

from sandro_slam.factors import gaussian_noise

_BETWEEN = (gtsam.BetweenFactorPose2, gtsam.BetweenFactorPose3)


@dataclass
class _Run:
    """Plain poses `inner` between poses `start` and `end`; `steps`: the measured poses from each pose of the run
    to the next (start -> inner[0] -> ... -> end), oriented along it, and their covariances."""

    start: int
    end: int
    inner: list[int]
    steps: list[gtsam.Pose2 | gtsam.Pose3]
    covariances: list[np.ndarray]


@dataclass
class CondensedGraph:
    """`graph`'s factors on the kept poses, in their order, then one between factor per run of plain poses."""

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values  # of the kept poses
    known_inliers: list[int]  # into `graph`: the known inliers kept and every condensed factor
    original: np.ndarray  # per factor of `graph` its index in the whole graph; -1 for a condensed one
    hidden_dims: int  # measurement dimensions (= unknowns) the condensing removed
    runs: list[_Run]

    def weights_of_whole(self, weights: np.ndarray, size: int) -> np.ndarray:
        """Weights (size,) of the whole graph's factors: those of the kept factors, 1 for every condensed one's."""
        whole = np.ones(size)
        kept = self.original >= 0
        whole[self.original[kept]] = weights[kept]
        return whole

    def values_of_whole(self, values: gtsam.Values) -> gtsam.Values:
        """`values` of the kept poses, and every plain pose composed along its run from the run's start."""
        whole = gtsam.Values(values)
        for run in self.runs:
            pose = values.atPose3(run.start) if isinstance(run.steps[0], gtsam.Pose3) else values.atPose2(run.start)
            for key, step in zip(run.inner, run.steps[:-1]):
                pose = pose.compose(step)
                whole.insert(key, pose)
        return whole


def condensed(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int]
) -> CondensedGraph | None:
    """`graph` with its runs of plain poses condensed (module docstring); None where no pose is plain, or a run
    closes on itself."""
    known = set(known_inliers)
    touching = Counter(key for i in range(graph.size()) for key in graph.at(i).keys())
    odometry: dict[int, list[int]] = {}
    for index in known_inliers:
        factor = graph.at(index)
        if isinstance(factor, _BETWEEN) and not isinstance(factor.noiseModel(), gtsam.noiseModel.Robust):
            a, b = factor.keys()
            if a != b:
                odometry.setdefault(a, []).append(index)
                odometry.setdefault(b, []).append(index)
    plain = {
        key
        for key, count in touching.items()
        if count == 2 and len(odometry.get(key, [])) == 2 and len({_other(graph, i, key) for i in odometry[key]}) == 2
    }
    if not plain:
        return None
    runs, used = [], set()
    for start in sorted(set(odometry) - plain):
        for index in odometry[start]:
            if index in used or _other(graph, index, start) not in plain:
                continue
            run = _walk(graph, odometry, plain, start, index, used)
            if run.end == run.start:
                return None
            runs.append(run)
    if sum(len(run.inner) for run in runs) != len(plain):  # a ring of plain poses that nothing else touches
        return None
    out = CondensedGraph(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], np.zeros(0, dtype=int), 0, runs)
    original = []
    for index in range(graph.size()):
        factor = graph.at(index)
        if any(key in plain for key in factor.keys()):
            continue
        if index in known:
            out.known_inliers.append(out.graph.size())
        out.graph.add(factor)
        original.append(index)
    for run in runs:
        out.known_inliers.append(out.graph.size())
        out.graph.add(_condensed_factor(run))
        original.append(-1)
    out.original = np.array(original, dtype=int)
    out.initial = gtsam.Values(initial)
    for key in plain:
        out.initial.erase(key)
    dim = 6 if isinstance(runs[0].steps[0], gtsam.Pose3) else 3
    out.hidden_dims = dim * len(plain)
    return out


def _other(graph: gtsam.NonlinearFactorGraph, index: int, key: int) -> int:
    a, b = graph.at(index).keys()
    return b if a == key else a


def _walk(
    graph: gtsam.NonlinearFactorGraph,
    odometry: dict[int, list[int]],
    plain: set[int],
    start: int,
    index: int,
    used: set[int],
) -> _Run:
    """The run from `start` through the odometry factor `index` to the next pose that is not plain."""
    run = _Run(start, start, [], [], [])
    key = start
    while True:
        used.add(index)
        factor = graph.at(index)
        covariance = np.asarray(gaussian_noise(factor).covariance())
        if factor.keys()[0] == key:
            run.steps.append(factor.measured())
            run.covariances.append(covariance)
        else:  # the inverse measurement: its right perturbation is the measured one's moved through its adjoint
            adjoint = factor.measured().AdjointMap()
            run.steps.append(factor.measured().inverse())
            run.covariances.append(adjoint @ covariance @ adjoint.T)
        key = _other(graph, index, key)
        if key not in plain:
            run.end = key
            return run
        run.inner.append(key)
        index = next(i for i in odometry[key] if i != index)


def _condensed_factor(run: _Run) -> gtsam.NonlinearFactor:
    """One between factor from the run's start to its end: its steps composed, each step's covariance moved to the
    end's frame through the adjoint of the steps after it (right perturbations)."""
    pose, covariance = run.steps[0], run.covariances[0]
    for step, step_covariance in zip(run.steps[1:], run.covariances[1:]):
        adjoint = step.inverse().AdjointMap()
        pose, covariance = pose.compose(step), adjoint @ covariance @ adjoint.T + step_covariance
    factor_type = gtsam.BetweenFactorPose3 if isinstance(pose, gtsam.Pose3) else gtsam.BetweenFactorPose2
    covariance = 0.5 * (covariance + covariance.T)
    return factor_type(run.start, run.end, pose, gtsam.noiseModel.Gaussian.Covariance(covariance))
