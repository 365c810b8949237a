"""Fixtures shared by the sandro_slam tests."""

import numpy as np
import pytest

from pipelines.simulation import simulate_sequence

KEYFRAME_STEP = 40  # frames (40 m) between the keyframes of the drive


@pytest.fixture(scope="session")
def drive():
    """Keyframes of the two-lap simulated drive: deskewed scans, true poses and drifting odometry poses."""
    sequence = simulate_sequence(seed=0)
    indices = np.arange(0, len(sequence), KEYFRAME_STEP)
    truth, scans = [], []
    for i in indices:
        scan, T = sequence.deskewed(int(i))
        truth.append(T)
        scans.append(scan.points)
    # Odometry that turns 0.2 degree too far per keyframe: about 8 m of drift at the end of lap 1.
    drift = np.eye(4)
    drift[:2, :2] = [[np.cos(0.0035), -np.sin(0.0035)], [np.sin(0.0035), np.cos(0.0035)]]
    odometry = [truth[0]]
    for a, b in zip(truth[:-1], truth[1:]):
        odometry.append(odometry[-1] @ np.linalg.inv(a) @ b @ drift)
    return np.array(truth), np.array(odometry), scans
