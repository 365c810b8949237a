"""sandro_slam.background: loop closure in a worker process, and the module's pickling that carries it."""

import os
import pickle

import numpy as np
import pytest

from pipelines.simulation import simulate_sequence
from sandro_slam import LoopClosureModule, OfflineSlam, SlamConfig
from sandro_slam.background import BackgroundLoopClosure


def _config(mode: str = "batch") -> SlamConfig:
    config = SlamConfig()
    config.graph.mode = mode
    config.loops.map_closures_spacing = 0.0  # MapClosures sees every keyframe of the drive (40 m apart)
    return config


def _loops(module: LoopClosureModule) -> list[tuple]:
    return [(loop.source_key, loop.target_key, loop.found_by, loop.weight >= 0.5) for loop in module.loops]


@pytest.fixture(scope="module")
def inline(drive):
    """The module run in this process over the drive's keyframes, and its optimised poses."""
    _, odometry, scans = drive
    module = LoopClosureModule(_config())
    for key, (T, points) in enumerate(zip(odometry, scans)):
        module.add_keyframe(key, T, points)
    return module, module.optimize()


@pytest.mark.slow
def test_the_worker_returns_what_the_module_gives_in_this_process(drive, inline):
    _, odometry, scans = drive
    expected, expected_poses = inline
    with BackgroundLoopClosure(LoopClosureModule(_config())) as background:
        for key, (T, points) in enumerate(zip(odometry, scans)):
            background.add_keyframe(key, T, points)
        module, poses, cpu_seconds = background.finish()
    assert len(expected.loops) >= 3 and _loops(module) == _loops(expected)
    for loop, reference in zip(module.loops, expected.loops):
        np.testing.assert_array_equal(loop.T_target_source, reference.T_target_source)
        np.testing.assert_array_equal(loop.covariance, reference.covariance)
    assert module.graph.size() == expected.graph.size() and module.attempts == expected.attempts
    for key, pose in expected_poses.items():
        np.testing.assert_array_equal(poses[key], pose)
    assert cpu_seconds > 0.0


@pytest.mark.parametrize("mode", ["batch", "incremental"])
def test_a_module_unpickled_halfway_goes_on_as_the_original(drive, inline, mode):
    # Submap descriptions and MapClosures' database do not pickle: they are made again from the submaps.
    _, odometry, scans = drive
    module = LoopClosureModule(_config(mode))
    half = len(scans) // 2
    for key in range(half):
        module.add_keyframe(key, odometry[key], scans[key])
    module = pickle.loads(pickle.dumps(module))
    assert module.closer._descriptions == {}
    for key in range(half, len(scans)):
        module.add_keyframe(key, odometry[key], scans[key])
    poses = module.optimize()
    expected, expected_poses = inline
    assert _loops(module) == _loops(expected)
    for key, pose in expected_poses.items():
        np.testing.assert_allclose(poses[key][:3, 3], pose[:3, 3], atol=0.05 if mode == "incremental" else 1e-6)


def test_the_worker_s_error_is_raised_by_finish():
    with BackgroundLoopClosure(LoopClosureModule(_config())) as background:
        background.add_keyframe(0, np.eye(4), np.zeros((5, 2)))
        with pytest.raises(ValueError, match=r"keyframe 0: points must be an \(N, 3\) array"):
            background.finish()


def test_a_worker_that_dies_is_reported():
    with BackgroundLoopClosure(LoopClosureModule(_config())) as background:
        background._process.kill()
        background.add_keyframe(0, np.eye(4), np.zeros((20, 3)))
        with pytest.raises(RuntimeError, match="loop-closure worker process ended with exit code -9"):
            background.finish()


@pytest.mark.slow
def test_offline_slam_takes_the_module_back_from_its_worker(monkeypatch):
    sequence = simulate_sequence(seed=1, frames=25)
    frames = list(sequence.frames())
    slam = OfflineSlam(SlamConfig())
    result = slam.run(frames)
    assert len(result.keyframes) >= 2
    assert result.timings["loop_closure_worker_cpu"] > 0.0
    assert result.graph is slam.module.graph and slam.module.values.size() == len(result.keyframes)

    config = SlamConfig()
    config.loops.in_background = False
    inline = OfflineSlam(config).run(frames)
    assert "loop_closure_worker_cpu" not in inline.timings
    assert len(inline.keyframes) == len(result.keyframes)

    import sandro_slam.offline

    monkeypatch.setattr(sandro_slam.offline, "usable_cores", lambda: 1)  # one core: no idle cycles to use
    assert "loop_closure_worker_cpu" not in OfflineSlam(SlamConfig()).run(frames).timings


def test_the_worker_imports_from_where_the_caller_does(tmp_path, monkeypatch):
    from sandro_slam.background import worker_environment

    monkeypatch.syspath_prepend(str(tmp_path))  # as a script that adds a checkout to sys.path
    assert str(tmp_path) in worker_environment()["PYTHONPATH"].split(os.pathsep)
