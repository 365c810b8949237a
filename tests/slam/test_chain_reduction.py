import gtsam
import numpy as np
import pytest

from sandro_slam import robust_backend
from sandro_slam.chain_reduction import condensed
from sandro_slam.config import GraphConfig
from sandro_slam.covariance import FactorCovariances
from sandro_slam.robust_backend import robust_optimize


def _square_walk(is3d: bool, laps: int = 3, side: int = 25, seed: int = 0):
    """A walk of `laps` laps around a square of `side` poses a side (1 m steps, a 90 deg turn at each corner), its
    odometry noisy and drifting, a loop from each corner pose of every lap after the first to the same corner of the
    first lap (and one pose on), some odometry steps walked backwards (factors from the later pose): (graph,
    initial values from the odometry, known-inlier indices, loop indices, true poses)."""
    rng = np.random.default_rng(seed)
    n = 4 * side * laps
    truth = [np.eye(4)]
    for i in range(1, n):
        yaw = np.pi / 2 if i % side == 0 else 0.0
        step = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(1.0, 0.0, 0.0)).matrix()
        truth.append(truth[-1] @ step)
    sigmas = np.array([0.002] * 3 + [0.01] * 3)
    kind = (gtsam.Pose3, gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3) if is3d else (
        gtsam.Pose2, gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2)  # fmt: skip

    def pose(T: np.ndarray):
        if is3d:
            return gtsam.Pose3(T)
        return gtsam.Pose2(T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0]))

    def noisy(T: np.ndarray, drift: float):
        delta = rng.normal(scale=sigmas) + np.array([0.0, 0.0, drift, 0.0, 0.0, 0.0])
        if not is3d:  # in the plane
            delta[[0, 1, 5]] = 0.0
        return T @ gtsam.Pose3.Expmap(delta).matrix()

    if is3d:
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    else:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigmas[3], sigmas[4], sigmas[2]]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(kind[2](0, kind[0](), noise))
    initial = gtsam.Values()
    initial.insert(0, kind[0]())
    for i in range(1, n):
        step = noisy(np.linalg.inv(truth[i - 1]) @ truth[i], 5e-4)
        if i % 7 == 3:  # written from the later pose
            graph.add(kind[1](i, i - 1, pose(np.linalg.inv(step)), noise))
        else:
            graph.add(kind[1](i - 1, i, pose(step), noise))
        initial.insert(i, initial.atPose3(i - 1).compose(pose(step)) if is3d else
                       initial.atPose2(i - 1).compose(pose(step)))  # fmt: skip
    known = list(range(graph.size()))
    for lap in range(1, laps):
        for corner in range(4):
            for offset in (0, 1):
                a, b = corner * side + offset, (4 * lap + corner) * side + offset
                graph.add(kind[1](a, b, pose(noisy(np.linalg.inv(truth[a]) @ truth[b], 0.0)), noise))
    return graph, initial, known, list(range(len(known), graph.size())), truth


def _pose_matrix(values: gtsam.Values, key: int, is3d: bool) -> np.ndarray:
    if is3d:
        return values.atPose3(key).matrix()
    p = values.atPose2(key)
    T = np.eye(4)
    T[:2, :2] = p.rotation().matrix()
    T[:2, 3] = [p.x(), p.y()]
    return T


@pytest.mark.parametrize("is3d", [False, True])
def test_the_condensed_graph_has_the_optimum_and_the_covariances_of_the_whole_on_the_poses_it_keeps(is3d):
    graph, initial, known, loops, _ = _square_walk(is3d)
    reduced = condensed(graph, initial, known)
    assert reduced is not None
    kept_keys = set(reduced.initial.keys())
    assert len(kept_keys) == 1 + 2 * 4 * 3  # the first pose, the loops' poses (corners and the pose after each)
    assert reduced.hidden_dims == (6 if is3d else 3) * (len(graph.keyVector()) - len(kept_keys))
    assert list(reduced.original[reduced.original >= 0]) == sorted(
        set(range(graph.size())) - {i for i in known if any(k not in kept_keys for k in graph.at(i).keys())}
    )
    whole = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    part = gtsam.LevenbergMarquardtOptimizer(reduced.graph, reduced.initial).optimize()
    covariances_whole = FactorCovariances(graph, whole)
    covariances_part = FactorCovariances(reduced.graph, part)
    for key in sorted(kept_keys)[1:]:
        difference = np.linalg.inv(_pose_matrix(whole, key, is3d)) @ _pose_matrix(part, key, is3d)
        a, b = covariances_whole.block(key, key), covariances_part.block(key, key)
        position = slice(3, 6) if is3d else slice(0, 2)
        sigma = np.sqrt(np.linalg.eigvalsh(a[position, position]).max())
        assert np.linalg.norm(difference[:3, 3]) < 0.2 * sigma  # exact for a linear graph; here to first order
        assert np.linalg.norm(a - b) < 0.02 * np.linalg.norm(a)


@pytest.mark.parametrize("is3d", [False, True])
def test_the_poses_of_a_run_are_composed_from_its_start(is3d):
    graph, initial, known, _, _ = _square_walk(is3d)
    reduced = condensed(graph, initial, known)
    whole = reduced.values_of_whole(reduced.initial)
    assert set(whole.keys()) == set(initial.keys())
    for key in initial.keys():  # the initial values are the odometry composed along the walk: the same again
        assert np.allclose(_pose_matrix(whole, key, is3d), _pose_matrix(initial, key, is3d), atol=1e-6)


def test_a_graph_whose_poses_all_hold_loops_is_not_condensed():
    graph, initial, known, _, _ = _square_walk(False, laps=2, side=3)
    for key in range(1, 12):
        graph.add(gtsam.BetweenFactorPose2(key, 12 + key, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    assert condensed(graph, initial, known) is None


def test_the_robust_back_end_decides_the_same_on_the_condensed_graph(monkeypatch):
    graph, initial, known, loops, truth = _square_walk(True)
    rng = np.random.default_rng(1)
    wrong = []
    for _ in range(6):  # wrong loops between random poses: 3 m and 0.2 rad off the truth
        a, b = (int(k) for k in sorted(rng.choice(len(truth), 2, replace=False)))
        offset = gtsam.Pose3.Expmap(np.array([0.0, 0.0, 0.2, 3.0, 0.0, 0.0])).matrix()
        wrong.append(graph.size())
        measured = gtsam.Pose3(np.linalg.inv(truth[a]) @ truth[b] @ offset)
        graph.add(gtsam.BetweenFactorPose3(a, b, measured, gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    values, weights = robust_optimize(graph, initial, known, GraphConfig())
    monkeypatch.setattr(robust_backend, "condensed", lambda *args: None)
    values_whole, weights_whole = robust_optimize(graph, initial, known, GraphConfig())
    assert np.array_equal(weights, weights_whole)
    assert np.all(weights[wrong] < 0.5) and np.mean(weights[loops] >= 0.5) > 0.9
    for key in initial.keys():
        assert np.allclose(values.atPose3(key).matrix(), values_whole.atPose3(key).matrix(), atol=1e-6)
