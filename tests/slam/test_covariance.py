"""FactorCovariances: every block a factor touches equals gtsam's marginals."""

import gtsam
import numpy as np
import pytest

from sandro_slam.covariance import FactorCovariances


def _loop_graph(is3d: bool, poses: int = 40, loops: int = 15, seed: int = 0):
    """A noisy odometry chain with a prior and random loops; the values are perturbed ground truth."""
    rng = np.random.default_rng(seed)
    if is3d:
        pose = gtsam.Pose3
        noise = gtsam.noiseModel.Gaussian.Covariance(np.diag(rng.uniform(0.01, 0.1, 6)) + 0.001)

        def random_pose(scale):
            return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3 * scale, 3)), rng.normal(0, scale, 3))

        between, prior = gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)
    else:
        pose = gtsam.Pose2
        noise = gtsam.noiseModel.Gaussian.Covariance(np.diag(rng.uniform(0.01, 0.1, 3)) + 0.001)

        def random_pose(scale):
            return gtsam.Pose2(*rng.normal(0, scale, 2), rng.normal(0, 0.3 * scale))

        between, prior = gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
    truth = [pose()]
    for _ in range(poses - 1):
        truth.append(truth[-1].compose(random_pose(1.0)))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(prior(0, truth[0], prior_noise))
    for i in range(poses - 1):
        graph.add(between(i, i + 1, truth[i].between(truth[i + 1]).compose(random_pose(0.01)), noise))
    for _ in range(loops):
        a, b = sorted(rng.choice(poses, 2, replace=False))
        graph.add(between(int(a), int(b), truth[a].between(truth[b]), noise))
    values = gtsam.Values()
    for i, T in enumerate(truth):
        values.insert(i, T.compose(random_pose(0.05)))
    return graph, values


@pytest.mark.parametrize("loops", [15, 150])  # the denser graph eliminates into supernodes of up to 20 poses
@pytest.mark.parametrize("is3d", [False, True])
def test_blocks_equal_gtsam_marginals(is3d, loops):
    graph, values = _loop_graph(is3d, loops=loops)
    covariances = FactorCovariances(graph, values)
    marginals = gtsam.Marginals(graph, values)
    for key in range(40):
        expected = marginals.marginalCovariance(key)
        np.testing.assert_allclose(
            covariances.block(key, key), expected, rtol=1e-8, atol=1e-12 * np.abs(expected).max()
        )
    for index in range(graph.size()):
        keys = graph.at(index).keys()
        if len(keys) != 2:
            continue
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector(list(keys))).fullMatrix()
        d = joint.shape[0] // 2
        np.testing.assert_allclose(covariances.block(*keys), joint[:d, d:], atol=1e-9 * np.abs(joint).max())
        np.testing.assert_allclose(covariances.block(keys[1], keys[0]), joint[d:, :d], atol=1e-9 * np.abs(joint).max())
        np.testing.assert_allclose(covariances.joint(list(keys)), joint, rtol=1e-8, atol=1e-9 * np.abs(joint).max())


@pytest.mark.parametrize("is3d", [False, True])
def test_mahalanobis_of_many_factors_is_each_factors_own(is3d):
    graph, values = _loop_graph(is3d, loops=30)
    covariances = FactorCovariances(graph, values)
    factors = [graph.at(i) for i in range(graph.size())]  # the prior and the between factors: two shapes
    drops = covariances.mahalanobis(factors, values, 1.0, -1.0)  # the cost drop of removing each factor
    innovations = covariances.mahalanobis(factors, values, 2.0, 0.5, correlated=False)
    for n, factor in enumerate(factors):
        b, M = covariances.projected(factor, values)
        np.testing.assert_allclose(drops[n], b @ np.linalg.solve(np.eye(len(b)) - M, b), rtol=1e-9)
        A, _ = factor.linearize(values).jacobian()
        d = A.shape[1] // len(factor.keys())
        blocks = [covariances.block(key, key) for key in factor.keys()]
        S = 2.0 * np.eye(len(b)) + 0.5 * sum(A[:, i * d : (i + 1) * d] @ C @ A[:, i * d : (i + 1) * d].T
                                             for i, C in enumerate(blocks))  # fmt: skip
        np.testing.assert_allclose(innovations[n], b @ np.linalg.solve(S, b), rtol=1e-9)


@pytest.mark.parametrize("is3d", [False, True])
def test_mahalanobis_of_factors_outside_the_graph_takes_their_joint_covariance(is3d):
    graph, values = _loop_graph(is3d, poses=60, loops=5)
    candidates, _ = _loop_graph(is3d, poses=60, loops=40, seed=1)  # loops the graph does not hold
    factors = [candidates.at(i) for i in range(60, candidates.size())]
    covariances = FactorCovariances(graph, values)
    marginals = gtsam.Marginals(graph, values)
    innovations = covariances.mahalanobis(factors, values, 0.5, 2.0)
    off_pattern = 0
    for n, factor in enumerate(factors):
        A, b = factor.linearize(values).jacobian()
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector(list(factor.keys()))).fullMatrix()
        expected = b @ np.linalg.solve(0.5 * np.eye(len(b)) + 2.0 * A @ joint @ A.T, b)
        np.testing.assert_allclose(innovations[n], expected, rtol=1e-8)
        try:
            covariances.joint(list(factor.keys()))
        except KeyError:
            off_pattern += 1
    assert off_pattern > 10  # most of them join poses that no factor and no elimination step joined


def test_pair_off_the_pattern_is_refused():
    graph, values = _loop_graph(False, poses=10, loops=0)  # a chain: eliminating it joins only neighbours
    covariances = FactorCovariances(graph, values)
    with pytest.raises(KeyError):
        covariances.block(0, 9)
    with pytest.raises(KeyError):
        covariances.joint([0, 9])


def test_undetermined_variable_is_refused():
    graph, values = _loop_graph(False, poses=10, loops=0)
    values.insert(99, gtsam.Pose2())  # no factor holds it
    with pytest.raises(ValueError):
        FactorCovariances(graph, values)


def test_a_floor_bounds_the_covariance_of_directions_no_factor_determines():
    graph, values = _loop_graph(False, poses=10, loops=0)
    values.insert(99, gtsam.Pose2())  # no factor holds it
    floored = FactorCovariances(graph, values, floor=1e-10)
    information, _ = graph.linearize(values).hessian()
    median = np.median(np.concatenate([np.diag(information), np.zeros(3)]))  # pose 99's diagonal: 0
    np.testing.assert_allclose(floored.block(99, 99), np.eye(3) / (1e-10 * median), rtol=1e-6, atol=1e-6)
    exact = FactorCovariances(graph, _without(values, 99))
    np.testing.assert_allclose(floored.block(5, 5), exact.block(5, 5), rtol=1e-6)  # the rest barely moves


def _without(values: gtsam.Values, key: int) -> gtsam.Values:
    out = gtsam.Values(values)
    out.erase(key)
    return out
