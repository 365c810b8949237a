"""sandro_core.register: recovery, invariance, calibration, bad input."""

from pathlib import Path

import gtsam
import numpy as np
import pytest

from pipelines.io.pointclouds import load_point_cloud
from pipelines.simulation.correspondences import make_problem, random_transform
from sandro_core import SandroConfig, register
from sandro_core import _kernels as K
from sandro_core.covariance import registration_information
from sandro_core.features import match_fpfh
from sandro_core.geometry import rotation_angle, transform_points
from sandro_core.registration import centred_single


def rotation_error_deg(T: np.ndarray, T_true: np.ndarray) -> float:
    return float(np.degrees(rotation_angle(T[:3, :3].T @ T_true[:3, :3])))


@pytest.mark.parametrize("outlier_rate", [0.0, 0.5, 0.9])
def test_exact_recovery_without_noise(outlier_rate):
    p = make_problem(np.random.default_rng(1), outlier_rate=outlier_rate, noise_sigma=0.0, noise_bound=0.01)
    result = register(p.source, p.target, SandroConfig(noise_bound=p.noise_bound))
    # Geman-McClure never gives outliers a weight of exactly zero: they pull by ~1e-8 m.
    np.testing.assert_allclose(result.transformation, p.T_target_source, atol=1e-6)
    assert result.valid
    assert set(result.inliers) == set(np.flatnonzero(p.inlier_mask))


@pytest.mark.parametrize("outlier_rate", [0.95, 0.99])
@pytest.mark.parametrize("kind", ["uniform", "structured"])
def test_high_outlier_rates(outlier_rate, kind):
    failures = 0
    for trial in range(10):
        p = make_problem(np.random.default_rng(100 + trial), outlier_rate=outlier_rate, outlier_kind=kind)
        result = register(p.source, p.target, SandroConfig(noise_bound=p.noise_bound))
        t_err = np.linalg.norm(result.transformation[:3, 3] - p.T_target_source[:3, 3])
        failures += rotation_error_deg(result.transformation, p.T_target_source) > 5.0 or t_err > 0.6
    assert failures <= 1


def test_paper_preset_runs_algorithm_1():
    p = make_problem(np.random.default_rng(2), outlier_rate=0.5)
    config = SandroConfig.paper().model_copy(update={"noise_bound": p.noise_bound})
    result = register(p.source, p.target, config)
    assert len(result.split_losses) == 4
    assert rotation_error_deg(result.transformation, p.T_target_source) < 5.0


def test_same_result_under_permutation():
    p = make_problem(np.random.default_rng(3), outlier_rate=0.8, outlier_kind="structured")
    config = SandroConfig(noise_bound=p.noise_bound)
    perm = np.random.default_rng(4).permutation(len(p.source))
    a = register(p.source, p.target, config)
    b = register(p.source[perm], p.target[perm], config)
    np.testing.assert_allclose(a.transformation, b.transformation, atol=1e-9)
    np.testing.assert_allclose(a.weights[perm], b.weights, atol=1e-9)


def test_seeded_and_deterministic():
    p = make_problem(np.random.default_rng(5), outlier_rate=0.9)
    config = SandroConfig(noise_bound=p.noise_bound, seed=7)
    a, b = register(p.source, p.target, config), register(p.source, p.target, config)
    np.testing.assert_array_equal(a.transformation, b.transformation)
    np.testing.assert_array_equal(a.weights, b.weights)


def test_covariance_is_calibrated():
    """Mean NEES over many noisy trials with outliers must be near the 6 degrees of freedom."""
    nees = []
    for trial in range(150):
        p = make_problem(np.random.default_rng(1000 + trial), n=300, outlier_rate=0.5, noise_sigma=0.01)
        result = register(p.source, p.target, SandroConfig(noise_bound=p.noise_bound))
        error = gtsam.Pose3.Logmap(gtsam.Pose3(p.T_target_source).between(gtsam.Pose3(result.transformation)))
        nees.append(error @ np.linalg.solve(result.covariance, error))
    assert 4.0 <= np.mean(nees) <= 8.0


def test_information_matches_gtsam_right_perturbation():
    """H = sum J^T J with J the numerical Jacobian of p - T.retract(xi) q in gtsam's [rot, trans] order."""
    rng = np.random.default_rng(6)
    q = rng.normal(size=(20, 3)) * 3.0
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.3, -0.2, 0.5), gtsam.Point3(1.0, 2.0, -3.0))
    eps = 1e-6
    H = np.zeros((6, 6))
    for qi in q:
        J = np.zeros((3, 6))
        for k in range(6):
            xi = np.zeros(6)
            xi[k] = eps
            J[:, k] = -(T.retract(xi).transformFrom(qi) - T.retract(-xi).transformFrom(qi)) / (2 * eps)
        H += J.T @ J
    np.testing.assert_allclose(registration_information(q, np.ones(len(q))), H, atol=1e-5)


def test_degenerate_geometry_is_invalid():
    rng = np.random.default_rng(8)
    line = np.outer(rng.uniform(-1, 1, 50), [1.0, 2.0, 3.0])
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]
    for source in (line, np.ones((50, 3))):
        result = register(source, transform_points(T, source), SandroConfig(noise_bound=0.05))
        assert not result.valid
        assert np.all(np.isfinite(result.transformation))


@pytest.mark.parametrize(
    ("source", "target", "message"),
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
        (np.zeros((5, 3)), np.zeros((4, 3)), "same number of rows"),
        (np.zeros((5, 2)), np.zeros((5, 2)), r"\(N, 3\)"),
        (np.zeros(15), np.zeros(15), r"\(N, 3\)"),
        (np.full((5, 3), np.nan), np.zeros((5, 3)), "NaN or inf"),
        (np.zeros((5, 3)), np.full((5, 3), np.inf), "NaN or inf"),
    ],
)
def test_bad_input_raises(source, target, message):
    with pytest.raises(ValueError, match=message):
        register(source, target)


def test_noise_bound_estimated_when_missing():
    p = make_problem(np.random.default_rng(9), outlier_rate=0.5)
    result = register(p.source, p.target)
    assert 0.0 < result.noise_bound < 0.5
    assert rotation_error_deg(result.transformation, p.T_target_source) < 5.0


def test_known_answer_on_the_real_small_gicp_pair():
    """The real pair (MIT, tests/data/small_gicp), the source moved far away: SANDRO on FPFH matches must land
    within 2 deg and 0.3 m of the ground truth."""
    data = Path(__file__).resolve().parents[1] / "data" / "small_gicp"
    source, target = load_point_cloud(data / "source.ply"), load_point_cloud(data / "target.ply")
    T_gt = np.loadtxt(data / "T_target_source.txt")
    for seed in range(3):
        T_move = random_transform(np.random.default_rng(seed), 10.0)
        P, Q = match_fpfh(transform_points(T_move, source), target, 0.5, source_viewpoint=T_move[:3, 3])
        result = register(P, Q, SandroConfig(noise_bound=0.5))
        T_true = T_gt @ np.linalg.inv(T_move)
        assert result.valid
        assert rotation_error_deg(result.transformation, T_true) < 2.0
        assert np.linalg.norm(result.transformation[:3, 3] - T_true[:3, 3]) < 0.3


@pytest.mark.parametrize("offset", [0.0, 5e5])  # a street around the origin, or in map (UTM-like) coordinates
def test_consistency_degrees_in_single_precision_match_double(offset):
    # The consensus stage ranks its seeds on centred float32 copies of the points: that must not change the
    # degrees it would get in float64 (uncentred, 5e5 m from the origin, some differ by up to 25).
    rng = np.random.default_rng(1)
    n = 2000
    src = rng.uniform(-100.0, 100.0, (n, 3)) + offset
    dst = src + rng.normal(0.0, 0.2, (n, 3)) + 50.0
    dst[: n // 2] = rng.uniform(-100.0, 150.0, (n // 2, 3)) + offset
    srcT, dstT = np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T)
    seeds = rng.permutation(n)[:500]
    double = K.consistency_degrees_serial(srcT, dstT, seeds, 0.5)
    single = K.consistency_degrees_serial(centred_single(srcT), centred_single(dstT), seeds, np.float32(0.5))
    assert double.mean() > 100  # the inliers' degrees are counted, not only outliers' zeros
    assert np.array_equal(single, double)
