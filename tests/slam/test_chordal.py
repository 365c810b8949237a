"""The chordal relaxation as the start of pose graph solves: graphs whose initial values say nothing."""

import gtsam
import numpy as np
import pytest

from sandro_slam.chordal import _anchored, _reweighted, _with_odometric_path, chordal_values
from sandro_slam.config import GraphConfig
from sandro_slam.robust_backend import robust_optimize


def _torus_poses(rings: int, per_ring: int) -> list[gtsam.Pose3]:
    """Poses on a torus (radii 12 m and 4 m), ring after ring, x along the ring, z out of the surface."""
    poses = []
    for i in range(rings):
        for j in range(per_ring):
            u, v = 2 * np.pi * (i + j / per_ring) / rings, 2 * np.pi * j / per_ring
            position = np.array([(12 + 4 * np.cos(v)) * np.cos(u), (12 + 4 * np.cos(v)) * np.sin(u), 4 * np.sin(v)])
            along = np.array([-np.sin(v) * np.cos(u), -np.sin(v) * np.sin(u), np.cos(v)])
            normal = np.array([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)])
            poses.append(gtsam.Pose3(gtsam.Rot3(np.column_stack([along, np.cross(normal, along), normal])), position))
    return poses


def _circle_poses(laps: int, per_lap: int) -> list[gtsam.Pose2]:
    """Poses driven around a 10 m circle `laps` times, heading along it."""
    angles = 2 * np.pi * np.arange(laps * per_lap) / per_lap
    return [gtsam.Pose2(10 * np.cos(a), 10 * np.sin(a), a + np.pi / 2) for a in angles]


def _graph(poses: list, period: int, n_wrong: int, seed: int, rotation_sigma: float):
    """Prior, noisy odometry, a noisy loop from every pose to the one `period` before, then `n_wrong` loops
    between random poses measuring a random relative pose. Returns (graph, known inlier indices, real loop
    count, identity initial values)."""
    rng = np.random.default_rng(seed)
    is3d = isinstance(poses[0], gtsam.Pose3)
    pose_type, between, prior = (
        (gtsam.Pose3, gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3)
        if is3d
        else (gtsam.Pose2, gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2)
    )
    sigmas = np.array([rotation_sigma] * 3 + [0.1] * 3) if is3d else np.array([0.1, 0.1, rotation_sigma])
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)

    def measured(a: int, b: int):
        return poses[a].between(poses[b]).compose(pose_type.Expmap(rng.normal(0.0, sigmas)))

    graph = gtsam.NonlinearFactorGraph()
    graph.add(prior(0, poses[0], gtsam.noiseModel.Isotropic.Sigma(len(sigmas), 1e-3)))
    for k in range(len(poses) - 1):
        graph.add(between(k, k + 1, measured(k, k + 1), noise))
    known = list(range(graph.size()))
    for k in range(period, len(poses)):
        graph.add(between(k - period, k, measured(k - period, k), noise))
    n_real = graph.size() - len(known)
    for _ in range(n_wrong):
        a, b = (int(i) for i in rng.choice(len(poses), 2, replace=False))
        if is3d:  # a random rotation and a translation within 5 m
            wrong = pose_type.Expmap(np.concatenate([rng.normal(0, 0.3, 3), rng.uniform(-5, 5, 3)]))
        else:
            wrong = pose_type.Expmap(np.array([*rng.uniform(-5, 5, 2), rng.normal(0, 0.3)]))
        graph.add(between(a, b, wrong, noise))
    initial = gtsam.Values()
    for k in range(len(poses)):
        initial.insert(k, pose_type())
    return graph, known, n_real, initial


def _lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> gtsam.Values:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setMaxIterations(500)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


@pytest.mark.parametrize("shape", ["torus", "circle"])
def test_least_squares_from_the_relaxation_reaches_a_lower_minimum_than_from_identity(shape):
    poses, period = (_torus_poses(20, 12), 12) if shape == "torus" else (_circle_poses(4, 30), 30)
    graph, _, _, identity = _graph(poses, period, n_wrong=0, seed=0, rotation_sigma=0.15 if shape == "torus" else 0.05)
    start = chordal_values(graph, identity)
    assert start is not None and set(start.keys()) == set(identity.keys())
    from_relaxation, from_identity = graph.error(_lm(graph, start)), graph.error(_lm(graph, identity))
    assert from_relaxation < 0.5 * from_identity
    truth = gtsam.Values()
    for k, pose in enumerate(poses):
        truth.insert(k, pose)
    assert from_relaxation <= graph.error(truth)  # the optimum lies below the truth's cost


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robust_back_end_from_identity_values_keeps_the_real_loops(seed):
    graph, known, n_real, identity = _graph(_torus_poses(20, 12), 12, n_wrong=40, seed=seed, rotation_sigma=0.15)
    _, weights = robust_optimize(graph, identity, known, GraphConfig())
    loops = weights[len(known) :] >= 0.5
    assert loops[:n_real].sum() >= 0.98 * n_real
    assert not loops[n_real:].any()


@pytest.mark.parametrize("shape", ["torus", "circle"])
def test_graphs_with_other_factors_have_no_relaxation(shape):
    poses = _torus_poses(2, 20) if shape == "torus" else _circle_poses(2, 20)
    graph, _, _, identity = _graph(poses, 20, n_wrong=0, seed=0, rotation_sigma=0.05)
    with_point = gtsam.NonlinearFactorGraph(graph)
    with_point.add(gtsam.PriorFactorPoint3(1000, gtsam.Point3(0, 0, 0), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    assert chordal_values(with_point, identity) is None


@pytest.mark.parametrize("shape", ["torus", "circle"])
def test_parts_no_factor_joins_each_have_a_relaxation_in_the_frame_of_their_first_pose(shape):
    poses = _torus_poses(2, 20) if shape == "torus" else _circle_poses(2, 20)
    graph, _, _, identity = _graph(poses, 20, n_wrong=0, seed=0, rotation_sigma=0.05)
    two_pieces = gtsam.NonlinearFactorGraph()  # the odometry without the prior and the step from pose 19 to 20
    for i in range(1, 40):
        if i != 20:
            two_pieces.add(graph.at(i))
    start = chordal_values(two_pieces, identity)
    assert start is not None and set(start.keys()) == set(identity.keys())
    assert two_pieces.error(start) == pytest.approx(0.0, abs=1e-6)  # chains alone: every step as measured
    for first in (0, 20):
        pose = start.atPose3(first) if shape == "torus" else start.atPose2(first)
        assert np.allclose(pose.matrix(), np.eye(len(pose.matrix())), atol=1e-2)


def test_odometry_with_a_gap_that_loops_bridge_has_a_relaxation():
    poses = _circle_poses(3, 20)
    graph, _, _, identity = _graph(poses, 20, n_wrong=0, seed=0, rotation_sigma=0.05)
    gapped = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        if graph.at(i).keys() != [29, 30]:  # odometry stops at pose 29 and starts again at 30
            gapped.add(graph.at(i))
    start = chordal_values(gapped, identity)
    assert start is not None
    truth = gtsam.Values()
    for k, pose in enumerate(poses):
        truth.insert(k, pose)
    assert gapped.error(_lm(gapped, start)) == pytest.approx(gapped.error(_lm(gapped, truth)), rel=1e-6)


def test_lago_takes_its_tree_across_a_gap_in_the_odometry_without_moving_its_relaxation():
    graph, _, _, identity = _graph(_circle_poses(3, 20), 20, n_wrong=0, seed=0, rotation_sigma=0.05)
    gapped = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        if graph.at(i).keys() != [29, 30]:
            gapped.add(graph.at(i))
    lago_input = _reweighted(_anchored(gapped, identity, is3d=False)[0], is3d=False)
    bridged, along_keys = _with_odometric_path(lago_input)
    assert along_keys and bridged.size() == lago_input.size() + 1
    general = gtsam.lago.initialize(lago_input, useOdometricPath=False)
    along = gtsam.lago.initialize(bridged, useOdometricPath=True)
    for k in range(60):
        np.testing.assert_allclose(along.atPose2(k).matrix(), general.atPose2(k).matrix(), atol=1e-6)
    renumbered = gtsam.NonlinearFactorGraph()  # keys 0, 2, 4, ...: no path along consecutive keys to take
    for i in range(lago_input.size()):
        factor = lago_input.at(i)
        if factor.size() == 2:
            a, b = factor.keys()
            renumbered.add(gtsam.BetweenFactorPose2(2 * a, 2 * b, factor.measured(), factor.noiseModel()))
    same, along_keys = _with_odometric_path(renumbered)
    assert same is renumbered and not along_keys


@pytest.mark.parametrize("shape", ["torus", "circle"])
def test_the_relaxation_lies_in_the_frame_of_the_tightest_prior(shape):
    poses = _torus_poses(1, 3) if shape == "torus" else _circle_poses(1, 3)
    graph, _, _, identity = _graph(poses, 3, n_wrong=0, seed=0, rotation_sigma=0.05)  # a tree: it fits exactly
    pose_type = type(poses[0])
    moved = pose_type.Expmap(np.array([0.1, 0.2, 0.3, 9.7, 5.3, 1.0][: 6 if shape == "torus" else 3]))
    loose = gtsam.NonlinearFactorGraph(graph)
    prior = gtsam.PriorFactorPose3 if shape == "torus" else gtsam.PriorFactorPose2
    loose.add(prior(1, moved, gtsam.noiseModel.Isotropic.Sigma(len(moved.logmap(moved)), 1e3)))
    start = chordal_values(loose, identity)
    assert start is not None
    assert graph.error(start) == pytest.approx(0.0, abs=1e-9)
    first = start.atPose3(0) if shape == "torus" else start.atPose2(0)
    assert np.allclose(first.matrix(), poses[0].matrix(), atol=1e-6)


def test_a_planar_graph_whose_covariances_leave_roll_and_pitch_free_has_a_relaxation():
    circle = _circle_poses(2, 20)
    poses = [gtsam.Pose3(gtsam.Rot3.Rz(p.theta()), [p.x(), p.y(), 0.0]) for p in circle]
    noise = gtsam.noiseModel.Diagonal.Sigmas([1e3, 1e3, 0.05, 0.1, 0.1, 0.1])  # roll and pitch: no information
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    for a, b in [(k, k + 1) for k in range(39)] + [(k - 20, k) for k in range(20, 40)]:
        graph.add(gtsam.BetweenFactorPose3(a, b, poses[a].between(poses[b]), noise))
    identity = gtsam.Values()
    for k in range(40):
        identity.insert(k, gtsam.Pose3())
    start = chordal_values(graph, identity)
    assert start is not None
    assert graph.error(start) == pytest.approx(0.0, abs=1e-6)


def test_lago_takes_its_tree_along_keys_in_order_whose_numbers_leave_gaps(monkeypatch):
    """A graph the robust back end condensed keeps its odometry between keys that follow each other with gaps in their
    numbers: the relaxation numbers them again and LAGO takes the odometry as its tree, the same relaxation."""
    graph, _, _, identity = _graph(_circle_poses(3, 20), 20, n_wrong=0, seed=0, rotation_sigma=0.05)
    spread, spread_identity = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            a, b = factor.keys()
            spread.add(gtsam.BetweenFactorPose2(3 * a, 3 * b, factor.measured(), factor.noiseModel()))
        else:
            spread.add(gtsam.PriorFactorPose2(3 * factor.keys()[0], factor.prior(), factor.noiseModel()))
    for key in identity.keys():
        spread_identity.insert(3 * key, identity.atPose2(key))
    along = []
    initialize = gtsam.lago.initialize
    monkeypatch.setattr(gtsam.lago, "initialize", lambda g, path=True: along.append(path) or initialize(g, path))
    start, spread_start = chordal_values(graph, identity), chordal_values(spread, spread_identity)
    assert along == [True, True]
    for key in identity.keys():
        np.testing.assert_allclose(spread_start.atPose2(3 * key).matrix(), start.atPose2(key).matrix(), atol=1e-9)
