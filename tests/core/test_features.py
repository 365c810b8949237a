"""match_fpfh on the small_gicp pair (MIT, tests/data/small_gicp) and on bad input."""

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from pipelines.simulation.correspondences import random_transform
from sandro_core.features import match_fpfh
from sandro_core.geometry import transform_points

DATA = Path(__file__).resolve().parents[1] / "data" / "small_gicp"
VOXEL = 0.5  # [m]


def _inlier_ratio(P: np.ndarray, Q: np.ndarray, T: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm(transform_points(T, P) - Q, axis=1) <= VOXEL))


def _points(name: str) -> np.ndarray:
    return np.asarray(o3d.io.read_point_cloud(str(DATA / name)).points)


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return _points("source.ply"), _points("target.ply"), np.loadtxt(DATA / "T_target_source.txt")


def test_matches_on_real_pair_are_many_and_often_inliers(pair):
    source, target, T = pair
    P, Q = match_fpfh(source, target, VOXEL)
    assert P.shape == Q.shape and P.shape[1] == 3 and P.dtype == np.float64
    assert 200 <= len(P) <= 5000
    assert _inlier_ratio(P, Q, T) > 0.3  # measured: 42 %
    assert _inlier_ratio(P, Q, T) * len(P) >= 100


def test_moving_the_source_with_its_viewpoint_keeps_the_inliers(pair):
    source, target, T = pair
    for seed in range(2):
        T_moved_source = random_transform(np.random.default_rng(seed), 10.0)
        moved = transform_points(T_moved_source, source)
        P, Q = match_fpfh(moved, target, VOXEL, source_viewpoint=T_moved_source[:3, 3])
        assert _inlier_ratio(P, Q, T @ np.linalg.inv(T_moved_source)) > 0.3


def test_matches_are_mutual_one_to_one(pair):
    source, target, _ = pair
    P, Q = match_fpfh(source, target, VOXEL)
    assert len(np.unique(P, axis=0)) == len(P)
    assert len(np.unique(Q, axis=0)) == len(Q)


def test_same_input_same_output(pair):
    source, target, _ = pair
    P1, Q1 = match_fpfh(source, target, VOXEL)
    P2, Q2 = match_fpfh(source, target, VOXEL)
    np.testing.assert_array_equal(P1, P2)
    np.testing.assert_array_equal(Q1, Q2)


@pytest.mark.parametrize(
    "source, target, voxel, message",
    [
        (np.empty((0, 3)), np.ones((10, 3)), 0.5, "empty"),
        (np.ones((10, 2)), np.ones((10, 3)), 0.5, r"\(N, 3\)"),
        (np.ones((10, 3)), np.full((10, 3), np.nan), 0.5, "NaN"),
        (np.ones((10, 3)), np.ones((10, 3)), 0.0, "voxel_size"),
        (np.ones((10, 3)), np.ones((10, 3)), float("nan"), "voxel_size"),
    ],
)
def test_bad_input_raises_value_error(source, target, voxel, message):
    with pytest.raises(ValueError, match=message):
        match_fpfh(source, target, voxel)


def test_bad_viewpoint_raises_value_error():
    with pytest.raises(ValueError, match="source_viewpoint"):
        match_fpfh(np.ones((10, 3)), np.ones((10, 3)), 0.5, source_viewpoint=np.zeros(2))


def test_mutual_matches_equal_a_full_search_both_ways():
    from scipy.spatial import cKDTree

    from sandro_core.features import mutual_matches

    rng = np.random.default_rng(0)
    source, target = rng.random((500, 33)), rng.random((700, 33))
    _, forward = cKDTree(target).query(source, k=1, eps=0.5)
    _, backward = cKDTree(source).query(target, k=1, eps=0.5)
    expected = np.flatnonzero(backward[forward] == np.arange(len(source)))
    for trees in [(None, None), (cKDTree(source), cKDTree(target))]:
        source_idx, target_idx = mutual_matches(source, target, *trees)
        np.testing.assert_array_equal(source_idx, expected)
        np.testing.assert_array_equal(target_idx, forward[expected])
    assert len(expected) > 0
