"""The worked example of a host-owned graph (examples/isam2_host.py): ISAM2 with odometry and GPS-like factors on
keys of its own takes the loops the LoopCloser proposes, the same loops a LoopClosureModule finds, and converges."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from sandro_slam import LoopClosureModule, SlamConfig

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "isam2_host.py"


def _example():
    spec = importlib.util.spec_from_file_location("isam2_host", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_an_isam2_host_with_gps_takes_the_loops_a_module_finds_and_converges():
    example = _example()
    data = example.keyframes(frames=480)  # 1.2 laps: the second lap closes loops on the first
    host = example.run(data)

    module = LoopClosureModule(SlamConfig())
    for key, _, T_odometry, points in data:
        module.add_keyframe(key, T_odometry, points)
    assert len(module.loops) >= 5
    assert {(loop.target_key, loop.source_key) for loop in host.loops} == {
        (X(loop.target_key), X(loop.source_key)) for loop in module.loops
    }
    assert host.kept.all()
    for loop, mine in zip(
        sorted(host.loops, key=lambda lp: lp.source_key), sorted(module.loops, key=lambda lp: lp.source_key)
    ):
        np.testing.assert_allclose(loop.T_target_source, mine.T_target_source, atol=0.05)

    estimate = {key: host.estimate.atPose3(key).matrix() for key in host.keys}
    assert example.position_rmse(estimate, host.truth) < 0.5 * example.position_rmse(host.odometry, host.truth)
