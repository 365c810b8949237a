"""Fixtures shared by the pipelines tests."""

import numpy as np
import pytest

from pipelines.io.session import write_session
from pipelines.simulation import simulate_sequence
from pipelines.simulation.correspondences import random_transform
from sandro_slam import OfflineSlam, SlamConfig, SlamResult


def _run(start_distance: float, frames: int = 50) -> SlamResult:
    sequence = simulate_sequence(seed=0, frames=frames, start_distance=start_distance)
    return OfflineSlam(SlamConfig()).run(sequence.frames())


@pytest.fixture(scope="session")
def results(tmp_path_factory):
    """Two results folders of short drives along the same street, the second starting 25 m further on."""
    folders = []
    for name, start in (("first", 0.0), ("second", 25.0)):
        folder = tmp_path_factory.mktemp(name)
        result = _run(start)
        write_session(folder, result)
        folders.append((folder, result))
    return folders


@pytest.fixture
def walk():
    """n -> (n, 4, 4) poses of a seeded random walk: each step a random rotation and up to 1 m."""

    def poses(n: int = 50) -> np.ndarray:
        rng = np.random.default_rng(0)
        out = [np.eye(4)]
        for _ in range(n - 1):
            out.append(out[-1] @ random_transform(rng, 1.0))
        return np.array(out)

    return poses
