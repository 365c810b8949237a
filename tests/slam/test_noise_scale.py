"""Variance component estimation of the odometry's noise against the loops (sandro_slam.noise_scale)."""

import gtsam
import numpy as np

from sandro_slam.factors import between_factor
from sandro_slam.noise_scale import rescale_odometry


def _circle(n: int = 60, radius: float = 20.0) -> list[np.ndarray]:
    poses = []
    for i in range(n):
        angle = 2 * np.pi * i / n
        T = np.eye(4)
        T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        T[:2, 3] = radius * np.cos(angle), radius * np.sin(angle)
        poses.append(T)
    return poses


def _noisy(T: np.ndarray, rng: np.random.Generator, sigma_rot: float, sigma_trans: float) -> np.ndarray:
    xi = np.r_[rng.normal(scale=sigma_rot, size=3), rng.normal(scale=sigma_trans, size=3)]
    return T @ gtsam.Pose3.Expmap(xi).matrix()


def _graph(odometry_steps, loops, truth):
    """(graph, values at the truth, odometry factor indices, loop factor indices): a prior on pose 0, the odometry
    steps with a loose model (0.01 rad, 0.1 m), the loops (a, b, T_a_b) with the noise they have (0.005 rad, 0.05 m)."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(truth[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    odometry_cov, loop_cov = np.diag([0.01**2] * 3 + [0.1**2] * 3), np.diag([0.005**2] * 3 + [0.05**2] * 3)
    odometry, loop_indices = [], []
    for i, step in enumerate(odometry_steps):
        odometry.append(graph.size())
        graph.add(between_factor(i, i + 1, step, odometry_cov))
    for a, b, T in loops:
        loop_indices.append(graph.size())
        graph.add(between_factor(a, b, T, loop_cov))
    values = gtsam.Values()
    pose = truth[0]
    values.insert(0, gtsam.Pose3(pose))
    for i, step in enumerate(odometry_steps):
        pose = pose @ step
        values.insert(i + 1, gtsam.Pose3(pose))
    return graph, values, odometry, loop_indices


def _error(values: gtsam.Values, truth: list[np.ndarray]) -> float:
    return float(
        np.sqrt(np.mean([np.sum((values.atPose3(i).translation() - T[:3, 3]) ** 2) for i, T in enumerate(truth)]))
    )


def test_a_perfect_odometry_is_trusted_over_noisy_loops():
    rng = np.random.default_rng(0)
    truth = _circle()
    steps = [np.linalg.inv(a) @ b for a, b in zip(truth[:-1], truth[1:])]  # exact
    loops = [(i, i + 30, _noisy(np.linalg.inv(truth[i]) @ truth[i + 30], rng, 0.005, 0.05)) for i in range(30)]
    graph, values, odometry, loop_indices = _graph(steps, loops, truth)
    plain = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    rescaled, scale = rescale_odometry(graph, values, odometry, loop_indices)
    assert scale < 0.05
    assert _error(rescaled, truth) < 0.3 * _error(plain, truth)


def test_an_odometry_worse_than_its_model_keeps_the_model_and_too_few_loops_change_nothing():
    rng = np.random.default_rng(1)
    truth = _circle()
    drift = gtsam.Pose3(gtsam.Rot3.Yaw(0.02), gtsam.Point3(0.15, 0.0, 0.0)).matrix()  # beyond 0.01 rad, 0.1 m a step
    steps = [np.linalg.inv(a) @ b @ drift for a, b in zip(truth[:-1], truth[1:])]
    loops = [(i, i + 30, _noisy(np.linalg.inv(truth[i]) @ truth[i + 30], rng, 0.005, 0.05)) for i in range(30)]
    graph, values, odometry, loop_indices = _graph(steps, loops, truth)
    assert rescale_odometry(graph, values, odometry, loop_indices)[1] == 1.0
    assert rescale_odometry(graph, values, odometry, loop_indices[:5])[1] == 1.0
