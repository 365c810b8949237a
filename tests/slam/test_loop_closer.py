"""LoopCloser: ring keys find a revisit that drift moved beyond the search radius; a verified loop further from the
estimate than the drift bound is dropped as an alias."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipelines.simulation import simulate_sequence
from sandro_core.geometry import transform_points
from sandro_slam import LoopCloser, SlamConfig


@pytest.fixture(scope="module")
def place() -> np.ndarray:
    """A street seen over 10 frames, in the first frame's frame."""
    sequence = simulate_sequence(seed=1, frames=10)
    poses = sequence.poses_at(np.array([frame.timestamp for frame in sequence.frames()]))
    return np.concatenate(
        [transform_points(np.linalg.inv(poses[0]) @ T, frame.points) for T, frame in zip(poses, sequence.frames())]
    )


def _at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _revisit(place: np.ndarray, estimate_x: float) -> list:
    """Keyframe 0 at the place; keyframe 1 elsewhere, 30 m back along x; keyframe 2 at the place again after 60 m
    more, whose estimate drift has moved to `estimate_x` [m] from keyframe 0 (the middles of the stretches the two
    submaps cover lie further apart still). The loops keyframe 2 closes."""
    config = SlamConfig()  # radius 25 m, 50 m of travel back at least, max_drift 0.1
    config.loops.use_map_closures = False
    closer = LoopCloser(config)
    elsewhere = np.random.default_rng(0).uniform([-30, -30, -2], [30, 30, 0], (20000, 3))
    assert closer.add_keyframe(0, _at(0.0), place) == []
    assert closer.add_keyframe(1, _at(-30.0), elsewhere, distance=30.0) == []
    return closer.add_keyframe(2, _at(estimate_x), place, distance=60.0)


def test_ring_keys_close_a_loop_beyond_the_radius_within_the_drift_bound(place):
    loops = _revisit(place, estimate_x=28.0)  # beyond the 25 m radius, within 25 + 0.1 x 90 m
    assert [(loop.target_key, loop.source_key, loop.found_by) for loop in loops] == [(0, 2, "ring_key")]
    np.testing.assert_allclose(loops[0].T_target_source, np.eye(4), atol=0.05)


def test_a_loop_beyond_the_drift_bound_is_dropped(place):
    assert _revisit(place, estimate_x=40.0) == []  # 40 m from where the loop puts it: more than 34 m


def _street_revisit(place: np.ndarray, estimate_error: tuple[int, np.ndarray] | None = None) -> list:
    """Keyframes 0-3 at x = 0, 4, 8, 12 m, each with the place in its frame; one elsewhere; then keyframe 5 back at x
    = 0 after 60 m more. `estimate_error`: (key, T) moves that keyframe's estimate by T. The loops keyframe 5
    closes: SANDRO's with its two nearest candidates (2, 1), and guided ones."""
    config = SlamConfig()
    config.loops.use_map_closures = False
    config.loops.ring_key_candidates = 0
    config.loops.guided_loops = 2
    closer = LoopCloser(config)
    for key, x in enumerate([0.0, 4.0, 8.0, 12.0]):
        estimate = _at(x) @ (estimate_error[1] if estimate_error and estimate_error[0] == key else np.eye(4))
        assert closer.add_keyframe(key, estimate, transform_points(np.linalg.inv(_at(x)), place), distance=4.0) == []
    elsewhere = np.random.default_rng(0).uniform([-30, -30, -2], [30, 30, 0], (20000, 3))
    assert closer.add_keyframe(4, _at(-30.0), elsewhere, distance=42.0) == []
    return closer.add_keyframe(5, _at(0.0), place, distance=60.0)


def _found(loops: list) -> list[tuple[int, str]]:
    return [(loop.target_key, loop.found_by) for loop in loops]


def test_two_agreeing_loops_guide_loops_to_the_next_candidates(place):
    loops = _street_revisit(place)
    assert _found(loops) == [(2, "radius"), (1, "radius"), (0, "guided"), (3, "guided")]
    for loop in loops:
        np.testing.assert_allclose(loop.T_target_source, np.linalg.inv(_at(4.0 * loop.target_key)), atol=0.05)
    assert loops[2].covariance is loops[0].covariance


def test_loops_that_disagree_guide_none(place):
    # Keyframe 1's estimate 3 m off: its loop places keyframe 5 3 m from where keyframe 2's loop does. One of the two
    # is wrong, or the estimates are; a loop predicted from either could be as wrong.
    shifted = np.eye(4)
    shifted[1, 3] = 3.0
    assert _found(_street_revisit(place, (1, shifted))) == [(2, "radius"), (1, "radius")]


def test_a_guided_loop_that_icp_moves_off_the_prediction_is_dropped(place):
    # Keyframe 0's estimate turned by 0.5 deg: the pose predicted in its frame is that far off, and ICP, converging
    # to the true pose, moves it beyond the 0.1 deg a guided loop may differ from its prediction.
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 0.5, degrees=True).as_matrix()
    assert _found(_street_revisit(place, (0, turned))) == [(2, "radius"), (1, "radius"), (3, "guided")]
