"""The sway of a sensor (a walker's, a hand's) told from a car's steady motion by its poses."""

from __future__ import annotations

import numpy as np

from sandro_core.geometry import rotation_angle

SWAY_DEG = 0.5  # [deg] a sensor sways when its rotation over a sweep changes by more than this from one sweep to
# the next (median): a walker's or a hand's sway (0.76-2.05 deg on the simulated walkers), not a car's steady motion
# (0.09-0.17 deg) (docs/benchmarks.md)


def sway_deg(poses: np.ndarray) -> float:
    """How much the sensor's rotation over a sweep changes from one sweep to the next [deg], median over the scans'
    poses (F, 4, 4), T_world_sensor in order: 0 for fewer than three."""
    if len(poses) < 3:
        return 0.0
    motions = np.linalg.inv(poses[:-1]) @ poses[1:]
    changes = np.swapaxes(motions[:-1, :3, :3], 1, 2) @ motions[1:, :3, :3]
    return float(np.degrees(np.median(rotation_angle(changes))))
