"""`sandro-bench merge`'s reference merge: perfect registration, sessions moved rigidly."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipelines.bench.merge import _joint_ate, _loops_against_truth, _perfectly_registered, _suite_sequences
from pipelines.evaluation import pose_errors
from sandro_slam.merge.loops import InterSessionLoop


def _drive(start: tuple[float, float], heading_deg: float, n: int = 60) -> np.ndarray:
    """(n, 4, 4) true poses 1 m apart along a straight street."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    heading = np.radians(heading_deg)
    poses[:, :3, :3] = Rotation.from_euler("z", heading).as_matrix()
    poses[:, 0, 3] = start[0] + np.arange(n) * np.cos(heading)
    poses[:, 1, 3] = start[1] + np.arange(n) * np.sin(heading)
    return poses


def _transform(yaw_deg: float, xyz, roll_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, roll_deg], degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T


# A drives east along y = 0; S starts 40 m north, drives south and then east along A's street.
TRUTH_A = _drive((0.0, 0.0), 0.0)
TRUTH_S = np.concatenate([_drive((20.0, 40.0), -90.0, 40), _drive((20.0, 0.0), 0.0, 40)])
T_A_WORLD = _transform(30.0, [5.0, -3.0, 1.0])
T_S_WORLD = _transform(-100.0, [60.0, 20.0, 0.0])


def test_error_free_sessions_are_placed_at_the_true_transform():
    T = _perfectly_registered(T_A_WORLD @ TRUTH_A, TRUTH_A, T_S_WORLD @ TRUTH_S, TRUTH_S)
    rotation_deg, translation_m = pose_errors(T, T_A_WORLD @ np.linalg.inv(T_S_WORLD))
    assert rotation_deg < 1e-4 and translation_m < 1e-9
    ates = _joint_ate([T_A_WORLD @ TRUTH_A, T @ T_S_WORLD @ TRUTH_S], [TRUTH_A, TRUTH_S])
    assert max(ates) < 1e-9


def test_a_session_bent_away_from_the_overlap_keeps_its_own_error():
    """S's own map is right along the shared street but its north leg is rolled 0.3 deg about a point 6 m
    north of the corner (beyond the overlap): registered perfectly on the street, the far end stays 0.18 m
    off, which is what the reference measures (the sessions' own errors, not the merge's)."""
    pivot = _transform(0.0, [20.0, 6.0, 0.0])
    bend = pivot @ _transform(0.0, [0.0, 0.0, 0.0], roll_deg=0.3) @ np.linalg.inv(pivot)
    north = TRUTH_S[:, 1, 3] > 6.0
    own_s = T_S_WORLD @ np.where(north[:, None, None], bend @ TRUTH_S, TRUTH_S)
    T = _perfectly_registered(T_A_WORLD @ TRUTH_A, TRUTH_A, own_s, TRUTH_S)
    placed, wanted = T @ own_s, T_A_WORLD @ TRUTH_S
    assert np.abs(placed[~north, :3, 3] - wanted[~north, :3, 3]).max() < 1e-9
    far_end = np.linalg.norm(placed[0, :3, 3] - wanted[0, :3, 3])
    assert far_end == pytest.approx(np.radians(0.3) * 34.0, rel=0.01)


def test_sessions_that_do_not_overlap_have_no_reference():
    far = _drive((100.0, 0.0), 0.0)
    with pytest.raises(ValueError, match="within 5.0 m"):
        _perfectly_registered(TRUTH_A, TRUTH_A, far, far)


def test_a_session_on_one_straight_street_gets_its_roll_from_the_frames_axes():
    """Positions along one straight street leave the roll about it open; the frames' axes pin it."""
    truth_s = _drive((10.0, 0.0), 0.0, 30)
    T_s_world = _transform(40.0, [3.0, 4.0, 0.0], roll_deg=0.5)
    T = _perfectly_registered(T_A_WORLD @ TRUTH_A, TRUTH_A, T_s_world @ truth_s, truth_s)
    rotation_deg, translation_m = pose_errors(T, T_A_WORLD @ np.linalg.inv(T_s_world))
    assert rotation_deg < 1e-4 and translation_m < 1e-9


def test_suite_sessions_are_two_or_three_different_sequences_of_one_site():
    assert [s.name for s in _suite_sequences("city_32_car, city_16_big_moving")] == [
        "city_32_car",
        "city_16_big_moving",
    ]
    for names, message in (
        ("city_32_car,garage_32_slow", "share a site"),
        ("city_32_car", "2 or 3"),
        ("city_32_car,city_32_car", "2 or 3"),
        ("city_32_car,city_16_big_moving,city_128_out_back,city_avia_deskewed", "2 or 3"),
        ("city_32_car,nowhere", "unknown suite sequences: nowhere"),
    ):
        with pytest.raises(ValueError, match=message):
            _suite_sequences(names)


def test_inter_session_loops_are_judged_against_the_anchors_truth():
    """Keyframes of two frames each, the anchor second in B's; a right loop kept, a wrong one (1 m off) kept and
    a right one (0.1 m off) rejected."""
    truth_a, truth_b = TRUTH_A[:4], TRUTH_S[40:44]
    step = _transform(0.0, [1.0, 0.0, 0.0])
    back = np.linalg.inv(step)
    a = SimpleNamespace(keys=[0, 1], keyframe_of_frame=np.array([0, 0, 1, 1]),
                        T_keyframe_frame=np.stack([np.eye(4), step, np.eye(4), step]))  # fmt: skip
    b = SimpleNamespace(keys=[0, 1], keyframe_of_frame=np.array([0, 0, 1, 1]),
                        T_keyframe_frame=np.stack([back, np.eye(4), back, np.eye(4)]))  # fmt: skip

    def loop(target_key: int, source_key: int, off_m: float, weight: float) -> InterSessionLoop:
        T = np.linalg.inv(truth_a[2 * target_key]) @ truth_b[2 * source_key + 1] @ _transform(0.0, [0.0, off_m, 0.0])
        return InterSessionLoop(0, target_key, 1, source_key, T, np.eye(6), 50, 0.9, "guided", weight=weight)

    result = SimpleNamespace(loops=[loop(0, 0, 0.0, 1.0), loop(1, 0, 1.0, 1.0), loop(1, 1, 0.1, 0.0)])
    metrics = _loops_against_truth([(a, truth_a, None), (b, truth_b, None)], result)
    assert metrics["inter_session_loops_wrong"] == 1
    assert metrics["inter_session_loops_wrong_kept"] == 1
    assert metrics["inter_session_loops_real_rejected"] == 1
    assert metrics["inter_session_loop_error_median_m"] == pytest.approx(0.1)
