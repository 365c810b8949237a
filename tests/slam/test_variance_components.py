"""Variance components: groups whose covariances understate their noise are found and weighed down."""

import gtsam
import numpy as np
import pytest

from sandro_slam.factors import between_factor
from sandro_slam.robust_backend import refined
from sandro_slam.variance_components import reweighted

STATED = 0.01  # every factor states this sigma [rad, m]


def _graph(loop_sigma: float, seed: int = 0, poses: int = 60, loops: int = 120):
    """A 3D odometry chain with the noise it states, loops with `loop_sigma` of noise stating STATED, a prior on the
    first pose: (graph, groups, truth, values at the least-squares solution)."""
    rng = np.random.default_rng(seed)

    def noisy(T: gtsam.Pose3, sigma: float) -> np.ndarray:
        return T.compose(gtsam.Pose3.Expmap(rng.normal(0.0, sigma, 6))).matrix()

    truth = [gtsam.Pose3()]
    for _ in range(poses - 1):
        step = gtsam.Pose3(gtsam.Rot3.Yaw(rng.uniform(-0.3, 0.3)), np.array([2.0, rng.normal(0, 0.2), 0.0]))
        truth.append(truth[-1].compose(step))
    covariance = np.eye(6) * STATED**2
    graph, groups = gtsam.NonlinearFactorGraph(), []
    graph.add(gtsam.PriorFactorPose3(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    groups.append(None)
    for i in range(poses - 1):
        graph.add(between_factor(i, i + 1, noisy(truth[i].between(truth[i + 1]), STATED), covariance))
        groups.append("odometry")
    for _ in range(loops):
        a, b = (int(k) for k in sorted(rng.choice(poses, 2, replace=False)))
        graph.add(between_factor(a, b, noisy(truth[a].between(truth[b]), loop_sigma), covariance))
        groups.append("loops")
    initial = gtsam.Values()
    for i, T in enumerate(truth):
        initial.insert(i, T)
    values = refined(graph, initial, np.ones(graph.size()))
    return graph, groups, truth, values


def _position_error(values: gtsam.Values, truth: list[gtsam.Pose3]) -> float:
    return float(
        np.sqrt(
            np.mean([np.sum((values.atPose3(i).translation() - T.translation()) ** 2) for i, T in enumerate(truth)])
        )
    )


def test_loops_noisier_than_stated_are_weighed_down_and_the_poses_improve():
    graph, groups, truth, values = _graph(loop_sigma=10 * STATED)
    scaled, solution, factors = reweighted(graph, values, np.ones(graph.size()), groups, "odometry")
    assert factors["odometry"] == 1.0
    assert 50.0 < factors["loops"] < 200.0  # 100 in variance
    assert _position_error(solution, truth) < 0.8 * _position_error(values, truth)
    loop = groups.index("loops")
    np.testing.assert_allclose(
        scaled.at(loop).noiseModel().covariance(), graph.at(loop).noiseModel().covariance() * factors["loops"]
    )


def test_groups_that_state_their_noise_keep_it():
    graph, groups, _, values = _graph(loop_sigma=STATED)
    _, _, factors = reweighted(graph, values, np.ones(graph.size()), groups, "odometry")
    assert factors["loops"] == pytest.approx(1.0, abs=0.3)


def test_rejected_factors_do_not_count():
    graph, groups, _, values = _graph(loop_sigma=STATED)
    wrong = between_factor(0, 30, np.eye(4), np.eye(6) * STATED**2)  # 60 m off: a wrong loop
    graph.add(wrong)
    groups.append("loops")
    weights = np.ones(graph.size())
    weights[-1] = 0.0
    _, _, factors = reweighted(graph, values, weights, groups, "odometry")
    assert factors["loops"] == pytest.approx(1.0, abs=0.3)


def test_a_reference_without_kept_factors_is_refused():
    graph, groups, _, values = _graph(loop_sigma=STATED)
    with pytest.raises(ValueError, match="reference group"):
        reweighted(graph, values, np.ones(graph.size()), groups, "wheel odometry")
