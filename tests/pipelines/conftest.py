"""Fixtures shared by the pipelines tests."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

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


def _sigint_default() -> None:
    """Ctrl-C back to its default in the child: a shell starts background jobs with SIGINT ignored, which a child
    inherits, and Python then installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def interrupted_slam():
    """(sandro-slam arguments, started: () -> bool, wait [s], settle [s]) -> (exit code, stderr): `sandro-slam` in a
    process group of its own, Ctrl-C sent to the group as a terminal does `settle` seconds after `started()` holds
    (or after `wait` seconds), then waited for."""

    def run(arguments: list[str], started, wait: float, settle: float = 0.0) -> tuple[int, str]:
        process = subprocess.Popen(
            [sys.executable, "-m", "pipelines.cli.slam", *arguments],
            cwd=Path(__file__).resolve().parents[2],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=_sigint_default,
        )
        deadline = time.monotonic() + wait
        while not started() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(settle)
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
        return process.returncode, stderr

    return run
