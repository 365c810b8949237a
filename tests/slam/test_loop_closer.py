"""LoopCloser: ring keys find a revisit that drift moved beyond the search radius; a verified loop further from the
estimate than the drift bound is dropped as an alias."""

import numpy as np
import pytest

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
