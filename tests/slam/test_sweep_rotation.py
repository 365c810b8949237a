"""sandro_slam.sweep_rotation: the off-prediction watch, the map fit and the search over sweep rotations."""

import numpy as np
import pytest

from sandro_slam.sweep_rotation import HISTORY, STEP_DEG, MapFit, OffPredictionWatch, best_sweep_rotation, turned


def _at(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def test_the_watch_flags_a_pose_far_off_its_prediction_only_once_it_has_a_history():
    watch = OffPredictionWatch()
    offsets = 0.01 * (1.0 + 0.1 * np.sin(np.arange(HISTORY)))  # a steady drive: about a centimetre a scan
    assert not watch.flags(_at(0.0), _at(1.0))  # no history yet: never flagged
    watch = OffPredictionWatch()
    assert not any(watch.flags(_at(0.0), _at(offset)) for offset in offsets)
    assert not watch.flags(_at(0.0), _at(0.03))  # 3x the median
    assert watch.flags(_at(0.0), _at(0.5))  # 50x
    assert not watch.flags(_at(0.0), _at(0.01))


def test_the_map_fit_is_zero_on_the_map_and_one_off_it():
    rng = np.random.default_rng(0)
    points = rng.uniform(-10.0, 10.0, (500, 3))
    fit = MapFit(points, reach=0.5)
    assert fit.cost(points, np.eye(4)) == 0.0
    assert fit.cost(points, _at(100.0)) == 1.0
    assert 0.0 < fit.cost(points, _at(0.2)) < fit.cost(points, _at(0.4)) < 1.0


@pytest.mark.parametrize("truth_deg", [-5.0, 2.0, 3.0, 6.0])
def test_the_search_keeps_the_sweep_rotation_that_fits_best(truth_deg):
    # A cost with its minimum at `truth_deg` about z: the search lands on the tried angle nearest to it.
    truth = np.radians([0.0, 0.0, truth_deg])
    tried = []

    def register(rotation_vector):
        tried.append(rotation_vector)
        return float(np.linalg.norm(rotation_vector - truth)), rotation_vector

    best = best_sweep_rotation((float(np.linalg.norm(truth)), np.zeros(3)), register)
    angles = np.radians(STEP_DEG) * np.array([0.5, 1.0, 2.0])
    expected = np.sign(truth_deg) * angles[np.argmin(np.abs(angles - abs(truth[2])))]
    assert np.allclose(best, [0.0, 0.0, expected])
    assert len(tried) == 8  # six directions, then half and twice the best


def test_the_search_keeps_the_prediction_where_nothing_fits_better():
    best = best_sweep_rotation((0.1, "prediction"), lambda rotation_vector: (0.2, "turned"))
    assert best == "prediction"


def test_turned_rotates_the_motion_at_the_end_of_the_sweep():
    motion = _at(1.0)
    out = turned(motion, np.radians([0.0, 0.0, 90.0]))
    assert np.allclose(out[:3, 3], motion[:3, 3])
    assert np.allclose(out[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
