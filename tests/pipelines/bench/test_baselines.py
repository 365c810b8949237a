"""Each baseline recovers a known transform on an easy synthetic problem with 50 % outliers."""

import numpy as np
import pytest

from pipelines.bench.baselines import BASELINES, gnc_tls
from pipelines.evaluation import pose_errors
from pipelines.simulation.correspondences import make_problem


@pytest.mark.parametrize("name", list(BASELINES))
@pytest.mark.parametrize("kind", ["uniform", "structured"])
def test_recovers_transform_with_half_outliers(name, kind):
    problem = make_problem(np.random.default_rng(7), n=500, outlier_rate=0.5, outlier_kind=kind)
    T = BASELINES[name](problem.source, problem.target, problem.noise_bound)
    rotation_error, translation_error = pose_errors(T, problem.T_target_source)
    assert T.shape == (4, 4)
    assert rotation_error < 2.0 and translation_error < 0.05


@pytest.mark.parametrize("name", list(BASELINES))
def test_deterministic(name):
    problem = make_problem(np.random.default_rng(3), n=300, outlier_rate=0.8)
    first = BASELINES[name](problem.source, problem.target, problem.noise_bound)
    np.testing.assert_array_equal(first, BASELINES[name](problem.source, problem.target, problem.noise_bound))


def test_registry_order_is_stable():
    assert list(BASELINES)[:4] == ["ransac_1e3", "ransac_1e5", "fgr", "gnc_tls"]


@pytest.mark.parametrize("name", list(BASELINES))
def test_bad_input_raises_value_error(name):
    with pytest.raises(ValueError):
        BASELINES[name](np.zeros((2, 3)), np.zeros((2, 3)), 0.1)
    with pytest.raises(ValueError):
        BASELINES[name](np.zeros((10, 3)), np.zeros((10, 3)), -1.0)


def test_gnc_tls_exact_without_noise_and_outliers():
    problem = make_problem(np.random.default_rng(1), n=100, outlier_rate=0.0, noise_sigma=0.0)
    np.testing.assert_allclose(gnc_tls(problem.source, problem.target, 0.01), problem.T_target_source, atol=1e-9)
