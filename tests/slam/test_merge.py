"""Map merging: two overlapping sessions join, aliased non-overlapping ones are refused, bad inputs get one line."""

import json

import numpy as np
import pytest

from pipelines.io.merge_results import merge_summary
from pipelines.simulation import CityLayout, SpinningLidar, build_city
from pipelines.simulation.trajectory import Route, Trajectory
from sandro_core.geometry import rotation_angle
from sandro_slam import Session, SlamConfig, merge_sessions
from sandro_slam.factors import odometry_covariance
from sandro_slam.merge.free_space import free_space_conflict, free_voxels
from sandro_slam.merge.graph import INTER_SESSION, build_graph
from sandro_slam.merge.loops import InterSessionLoop
from sandro_slam.session import SessionEdge

LAYOUT = CityLayout(blocks_x=6)
LIDAR = SpinningLidar(columns=450)


def _yaw(angle: float, x: float, y: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    T[:2, 3] = x, y
    return T


def synthetic_session(name: str, loop, start: float, keyframes: int, seed: int = 0) -> tuple[Session, np.ndarray]:
    """Keyframes every 10 m along a loop of the simulated city, each submap one static sweep in its own frame;
    odometry edges from the truth; the session's world frame is its first keyframe's. Returns the true poses."""
    world = build_city(seed, LAYOUT)
    scene = world.raycasting_scene()
    trajectory = Trajectory(Route(*loop, start=start), speed=10.0, accel_time=0.0)
    truth = trajectory.poses(np.arange(keyframes) * 1.0)
    submaps = {k: LIDAR.scan(scene, np.repeat(truth[k][None], LIDAR.columns, axis=0))[0] for k in range(keyframes)}
    poses = {k: np.linalg.inv(truth[0]) @ truth[k] for k in range(keyframes)}
    config = SlamConfig().graph
    edges = [
        SessionEdge(
            k, k + 1, np.linalg.inv(poses[k]) @ poses[k + 1], odometry_covariance(10.0, config), "odometry", True
        )
        for k in range(keyframes - 1)
    ]
    session = Session(
        name,
        list(range(keyframes)),
        poses,
        submaps,
        edges,
        np.arange(keyframes) * 1.0,
        np.arange(keyframes),
        np.tile(np.eye(4), (keyframes, 1, 1)),
    )
    return session, truth


@pytest.fixture(scope="module")
def overlapping():
    a, truth_a = synthetic_session("a", LAYOUT.loop, 0.0, 10)
    b, truth_b = synthetic_session("b", (70.0, 0.0, 210.0, 70.0), 330.0, 10)
    T_b = _yaw(2.0, 60.0, -40.0)  # an arbitrary frame for b: nothing may depend on it
    return a, b.moved(T_b), np.linalg.inv(truth_a[0]) @ truth_b[0] @ np.linalg.inv(T_b)


def test_two_overlapping_sessions_merge(overlapping):
    a, b, T_a_b = overlapping
    result = merge_sessions([a, b])
    assert result.ok and result.joined == ["a", "b"]
    T = result.T_merged_session["b"]
    assert np.linalg.norm(T[:3, 3] - T_a_b[:3, 3]) < 0.2
    assert np.degrees(rotation_angle(T[:3, :3].T @ T_a_b[:3, :3])) < 1.0
    assert sum(loop.weight >= 0.5 for loop in result.loops) >= 3
    conflicts = [loop.conflict for loop in result.loops if not np.isnan(loop.conflict)]
    assert len(conflicts) >= 3 and np.median(conflicts) < SlamConfig().merge.max_free_space_conflict / 2
    assert result.covariance["b"].shape == (6, 6) and np.all(np.linalg.eigvalsh(result.covariance["b"]) > 0)
    assert result.frame_poses["b"].shape == (10, 4, 4)
    assert set(result.variance_factors) == {"a", "b", "inter-session loops"}
    assert result.variance_factors["a"] == 1.0
    json.dumps(merge_summary(result))  # plain Python types only (guided loops once carried numpy booleans)


def test_aliased_non_overlapping_sessions_are_refused():
    """Around blocks (1, 1) and (5, 1): the same block template 280 m apart, never within sensor range of each
    other. The loops agree on the aliased shift; the free-space test refuses it."""
    a, _ = synthetic_session("a", (0.0, 0.0, 70.0, 70.0), 0.0, 8)
    b, _ = synthetic_session("b", (280.0, 0.0, 350.0, 70.0), 0.0, 8)
    result = merge_sessions([a, b.moved(_yaw(-1.0, 30.0, 20.0))])
    assert not result.ok and result.joined == ["a"] and "free space" in result.refused["b"]


def test_free_space_conflict_sees_an_object_where_the_street_was_empty():
    """Target: a wall 10 m ahead over flat ground 1.8 m below the sensor. The wall itself does not conflict;
    a pole 5 m ahead, where the target's rays to the wall passed, does."""
    y, z = np.meshgrid(np.arange(-10.0, 10.0, 0.5), np.arange(-1.8, 5.0, 0.5))
    wall = np.c_[np.full(y.size, 10.0), y.ravel(), z.ravel()]
    x, y = np.meshgrid(np.arange(-10.0, 10.0, 0.5), np.arange(-10.0, 10.0, 0.5))
    ground = np.c_[x.ravel(), y.ravel(), np.full(x.size, -1.8)]
    points = np.vstack([wall, ground])
    normals = np.vstack([np.tile([-1.0, 0.0, 0.0], (len(wall), 1)), np.tile([0.0, 0.0, 1.0], (len(ground), 1))])
    free, plane = free_voxels(points, normals, 0.5)
    assert plane is not None and abs(plane[2] + 1.8) < 1e-6
    hits, tested = free_space_conflict(free, plane, wall, np.eye(4), 0.5)
    assert hits == 0 and tested > 0.8 * len(wall)
    pole = np.c_[np.full(8, 5.0), np.zeros(8), np.linspace(-1.0, 2.5, 8)]
    hits, tested = free_space_conflict(free, plane, pole, np.eye(4), 0.5)
    assert tested == 8 and hits >= 6


def test_the_merged_graph_widens_every_loop_by_the_odometry_across_its_keyframes():
    def session(name: str, sigma: float) -> Session:
        odometry = [SessionEdge(k, k + 1, _yaw(0.0, 10.0, 0.0), np.eye(6) * sigma**2, "odometry", True) for k in (0, 1)]
        loop = SessionEdge(0, 2, _yaw(0.0, 20.0, 0.0), np.eye(6) * 1e-4, "loop", True)
        poses = {k: _yaw(0.0, 10.0 * k, 0.0) for k in range(3)}
        points = {k: np.zeros((1, 3)) for k in range(3)}
        return Session(
            name,
            [0, 1, 2],
            poses,
            points,
            odometry + [loop],
            np.arange(3.0),
            np.arange(3),
            np.tile(np.eye(4), (3, 1, 1)),
        )

    sessions = [session("a", 0.1), session("b", 0.2)]
    inter = InterSessionLoop(0, 2, 1, 1, np.eye(4), np.eye(6) * 1e-4, 50, 0.9, "guided", voted=True)
    T_merged = {0: np.eye(4), 1: np.eye(4)}
    plain, _, known, loop_factors, groups = build_graph(sessions, T_merged, [inter], 1e-3)
    widened = build_graph(sessions, T_merged, [inter], 1e-3, loop_submap_noise=True)[0]
    assert widened.size() == plain.size() and loop_factors[0][1] == plain.size() - 1
    # The variance components' groups: each session's factors, the inter-session loops; the prior is in none.
    assert groups == [None, 0, 0, 0, 1, 1, 1, INTER_SESSION]

    def variances(graph, index: int) -> np.ndarray:
        return np.diag(graph.at(index).noiseModel().covariance())

    intra_loops = [i for i in known if i and np.allclose(variances(plain, i), 1e-4)]
    assert len(intra_loops) == 2
    np.testing.assert_allclose(variances(widened, intra_loops[0]), 1e-4 + 2 * 0.1**2)  # keyframes 0 and 2 of a
    np.testing.assert_allclose(variances(widened, intra_loops[1]), 1e-4 + 2 * 0.2**2)
    np.testing.assert_allclose(variances(widened, plain.size() - 1), 1e-4 + 0.1**2 + 0.2**2)  # a's 2, b's 1
    for index in known:
        if index not in intra_loops:
            np.testing.assert_allclose(variances(widened, index), variances(plain, index))
