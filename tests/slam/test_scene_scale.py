"""Lengths that follow the scene: the measured scale, the resolved configuration, where each entry point takes it."""

import numpy as np
import pytest

from pipelines.simulation import make_sequence
from pipelines.simulation.sensor import PRESETS
from pipelines.simulation.sites import build_office
from pipelines.simulation.trajectory import PolylineRoute
from sandro_slam import OfflineSlam, SlamConfig
from sandro_slam.config import REFERENCE_NOISE_BOUND, REFERENCE_ODOMETRY_VOXEL
from sandro_slam.merge.pipeline import merge_config
from sandro_slam.scene_scale import REFERENCE_RANGE, SCALE_LIMITS, scene_scale
from sandro_slam.session import Session


def _shell(rng: np.random.Generator, radius: float, count: int = 5000) -> np.ndarray:
    """Points at ranges spread up to `radius` [m] around the sensor."""
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * rng.uniform(0.5, radius, size=(count, 1))


def test_the_scale_follows_the_ranges_and_stays_within_its_limits():
    rng = np.random.default_rng(0)
    garage = scene_scale([_shell(rng, 20.0) for _ in range(3)])
    assert garage == pytest.approx(0.9 * 20.0 / REFERENCE_RANGE, rel=0.05)
    assert scene_scale([_shell(rng, 4.0)]) == SCALE_LIMITS[0]  # a small room
    assert scene_scale([_shell(rng, 150.0)]) == SCALE_LIMITS[1]  # open country: never coarser than the reference
    assert scene_scale([_shell(rng, 150.0)], max_range=20.0) == pytest.approx(garage, rel=0.1)  # as KISS-ICP crops
    assert scene_scale([]) == SCALE_LIMITS[1]


def test_a_narrow_start_does_not_set_the_scale_of_a_wide_drive():
    rng = np.random.default_rng(1)
    narrow, wide = [_shell(rng, 20.0) for _ in range(10)], [_shell(rng, 33.0) for _ in range(40)]
    assert scene_scale(narrow + wide) == pytest.approx(0.9, rel=0.05)
    assert scene_scale(narrow) == pytest.approx(0.9 * 20.0 / REFERENCE_RANGE, rel=0.05)


def test_resolving_scales_what_is_left_unset_and_keeps_what_is_set(tmp_path):
    config = SlamConfig(keyframes={"distance": 3.0})
    assert not config.is_resolved
    resolved = config.resolved(0.5)
    assert resolved.is_resolved and resolved.scale == 0.5
    assert resolved.keyframes.distance == 3.0  # set by the user
    assert resolved.keyframes.submap_voxel == 0.25
    assert resolved.loops.exclude_recent == 25.0
    assert resolved.registration.fpfh_voxel == 0.625
    assert resolved.merge.guided_radius == 5.0
    assert resolved.odometry.mapping.voxel_size == 0.5 * REFERENCE_ODOMETRY_VOXEL
    assert resolved.registration.sandro.noise_bound == 0.5 * REFERENCE_NOISE_BOUND
    assert config.keyframes.submap_voxel is None  # a copy: the original is untouched
    assert SlamConfig().resolved().keyframes.distance == 10.0  # the reference values at scale 1
    assert SlamConfig(scale=0.2).resolved().keyframes.distance == pytest.approx(2.0)

    resolved.to_yaml(tmp_path / "config.yaml")  # what a results folder holds: runs again as it ran
    again = SlamConfig.from_yaml(tmp_path / "config.yaml")
    assert again == resolved and again.is_resolved
    lengths = again.resolved(0.9).model_dump(exclude={"scale"})
    assert lengths == resolved.model_dump(exclude={"scale"})  # nothing left to scale


def test_a_run_indoors_measures_a_small_scale_and_reports_the_values_used():
    site = build_office(0)
    route = PolylineRoute(site.paths["loop"], corner_radius=1.2, closed=True)
    sequence = make_sequence(site.world, route, PRESETS["vlp16"], speed=1.5, distance=3.0, seed=0)
    config = SlamConfig()
    config.loops.in_background = False
    result = OfflineSlam(config).run(sequence.frames())
    assert result.config.scale < 0.35
    assert result.config.is_resolved
    assert result.config.keyframes.distance == pytest.approx(10.0 * result.config.scale)
    assert config.scale is None  # the caller's configuration is left as it was
    fixed = SlamConfig(scale=0.5)
    fixed.loops.in_background = False
    assert OfflineSlam(fixed).run(sequence.frames()).config.scale == 0.5  # a scale set is not measured again


def test_a_merge_takes_the_sessions_scale_unless_one_is_set():
    def session(scale):
        return Session("s", [0], {0: np.eye(4)}, {0: np.zeros((1, 3))}, [], np.zeros(1), np.zeros(1, int),
                       np.eye(4)[None], scale)  # fmt: skip

    sessions = [session(0.3), session(0.5), session(None)]
    assert merge_config(SlamConfig(), sessions).scale == pytest.approx(0.4)
    assert merge_config(SlamConfig(scale=0.7), sessions).scale == 0.7
    assert merge_config(SlamConfig(), [session(None)]).scale == 1.0
