"""sandro_slam.loop_consistency and the seeded path of the robust back end on a graph large enough to use it."""

import gtsam
import numpy as np
import pytest

from sandro_slam.config import GraphConfig
from sandro_slam.loop_consistency import supported_loops
from sandro_slam.robust_backend import refined, robust_optimize

LAPS, PER_LAP = 3, 60  # poses: three laps of a circle of 60 poses, 2 m apart
ODOMETRY_SIGMAS = np.array([0.002] * 3 + [0.02] * 3)  # [rad], [m]
LOOP_SIGMAS = np.array([0.005] * 3 + [0.05] * 3)


def _pose(i: int) -> gtsam.Pose3:
    angle = 2 * np.pi * i / PER_LAP
    radius = 2.0 * PER_LAP / (2 * np.pi)
    position = gtsam.Point3(radius * np.cos(angle), radius * np.sin(angle), 0)
    return gtsam.Pose3(gtsam.Rot3.Yaw(angle + np.pi / 2), position)


def _laps(n_wrong: int, seed: int = 0, lone: tuple[int, int] | None = None):
    """Three laps with odometry drifting (a bias of 0.3 of its noise), a run of real loops from every lap to the
    next (pose i to i + PER_LAP, every second pose), `n_wrong` wrong loops between random poses and, if given,
    one real `lone` loop with no neighbour. Returns (graph, initial, known inliers, real loop indices, wrong
    loop indices, truth)."""
    rng = np.random.default_rng(seed)
    n = LAPS * PER_LAP
    truth = [_pose(i) for i in range(n)]
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    initial = gtsam.Values()
    initial.insert(0, truth[0])
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(ODOMETRY_SIGMAS)
    for i in range(1, n):
        error = gtsam.Pose3.Expmap(rng.normal(scale=ODOMETRY_SIGMAS) + 0.3 * ODOMETRY_SIGMAS)
        step = truth[i - 1].between(truth[i]).compose(error)
        graph.add(gtsam.BetweenFactorPose3(i - 1, i, step, odometry_noise))
        initial.insert(i, initial.atPose3(i - 1).compose(step))
    known = list(range(graph.size()))
    loop_noise = gtsam.noiseModel.Diagonal.Sigmas(LOOP_SIGMAS)
    pairs = [(i, i + PER_LAP) for i in range(0, n - PER_LAP, 2)] + ([lone] if lone else [])
    real = []
    for a, b in pairs:
        measured = truth[a].between(truth[b]).compose(gtsam.Pose3.Expmap(rng.normal(scale=LOOP_SIGMAS)))
        real.append(graph.size())
        graph.add(gtsam.BetweenFactorPose3(a, b, measured, loop_noise))
    wrong = []
    while len(wrong) < n_wrong:
        a, b = sorted(int(k) for k in rng.choice(n, 2, replace=False))
        if b - a < 2:
            continue
        measured = gtsam.Pose3(gtsam.Rot3.Yaw(rng.uniform(-0.5, 0.5)), gtsam.Point3(*rng.uniform(-5, 5, 3)))
        wrong.append(graph.size())
        graph.add(gtsam.BetweenFactorPose3(a, b, measured, loop_noise))
    return graph, initial, known, real, wrong, truth


def test_real_loops_in_runs_are_supported_and_wrong_loops_are_not():
    graph, _, known, real, wrong, _ = _laps(n_wrong=30)
    supported = supported_loops(graph, known)
    first = len(known)
    assert not supported[[i - first for i in wrong]].any()
    assert supported[[i - first for i in real]].mean() > 0.9


def test_two_wrong_loops_that_agree_only_with_each_other_are_not_supported():
    graph, _, known, _, _, truth = _laps(n_wrong=0)
    wrong = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), gtsam.Point3(4.0, -3.0, 1.0))
    noise = gtsam.noiseModel.Diagonal.Sigmas(LOOP_SIGMAS)
    for a, b in [(31, 151), (32, 152)]:  # the same wrong offset, between neighbouring poses: they agree
        graph.add(gtsam.BetweenFactorPose3(a, b, truth[a].between(truth[b]).compose(wrong), noise))
    assert not supported_loops(graph, known)[-2:].any()


def test_a_loop_of_another_factor_type_or_off_the_chains_is_never_supported():
    graph, _, known, _, _, truth = _laps(n_wrong=0)
    graph.add(gtsam.PriorFactorPose3(5, truth[5], gtsam.noiseModel.Isotropic.Sigma(6, 1.0)))
    assert not supported_loops(graph, known)[-1]
    assert not supported_loops(gtsam.NonlinearFactorGraph(), []).any()


@pytest.mark.parametrize("n_wrong", [15, 45])
def test_the_seeded_back_end_keeps_every_real_loop_and_rejects_every_wrong_one(n_wrong):
    """The real loops come in runs (they seed TLS), plus one lone real loop that only the innovation test can
    admit: drift makes its plain error large before the other loops are in."""
    graph, initial, known, real, wrong, truth = _laps(n_wrong=n_wrong, lone=(5, 2 * PER_LAP + 35))
    values, weights = robust_optimize(graph, initial, known, GraphConfig())
    assert np.all(weights[real] >= 0.5)
    assert np.all(weights[wrong] < 0.5)
    clean = np.ones(graph.size())
    clean[wrong] = 0.0
    optimum = refined(graph, initial, clean)
    offsets = [values.atPose3(i).translation() - optimum.atPose3(i).translation() for i in range(len(truth))]
    assert np.linalg.norm(offsets, axis=1).max() < 1e-3
