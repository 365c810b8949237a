"""A scan's rotation over its sweep, searched for where deskewing with the constant-velocity prediction lost a turn.

KISS-ICP deskews a scan with the motion of the scan before. Where the rotation rate steps within a sweep (a car
turning sharply into a corner, a jolt of a handheld sensor), the scan is bent by the change, and the rigid
registration of the bent scan stays near the prediction: a car's scan into a corner whose yaw rate stepped from 0
to 57 deg/s registered 0.35 deg beyond the straight prediction while it had turned 3.6 deg, and deskewing again
with that registered rotation leaves it there. Deskewed with rotations other than the prediction's and each
registered, the scan fits the map best near its true motion (`MapFit`: 0.047 there against 0.154 for the
prediction, in units of the kernel squared), so the search keeps the best fit.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TypeVar

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

TRIGGER_RATIO = 5.0  # search when a pose lies this many times farther from its prediction than the recent median
HISTORY = 20  # scans whose distance from their prediction makes that median
STEP_DEG = 3.0  # the rotation over a sweep tried beyond the prediction's about each sensor axis, both ways;
# the best is then tried at half and at twice that
TRIAL_STRIDE = 3  # each trial registers every this-th point of its source (a third of the cost); the rotation
# kept is registered again with all of them

Fit = TypeVar("Fit")


class OffPredictionWatch:
    """Flags a scan whose registered pose lies far from its constant-velocity prediction compared with the scans
    before it (the translation [m] between them; TRIGGER_RATIO times the median of the last HISTORY scans).

    On a steady drive a pose lies about a centimetre from its prediction a scan; at the first scan of a turn
    that the deskewing lost, half a metre."""

    def __init__(self) -> None:
        self._offsets: deque[float] = deque(maxlen=HISTORY)

    def flags(self, prediction: np.ndarray, pose: np.ndarray) -> bool:
        """Whether `pose` (4x4, T_world_sensor) is far off `prediction`; the offset joins the history."""
        offset = float(np.linalg.norm(pose[:3, 3] - prediction[:3, 3]))
        far = len(self._offsets) == HISTORY and offset > TRIGGER_RATIO * float(np.median(self._offsets))
        self._offsets.append(offset)
        return far


class MapFit:
    """The cost of points placed on a map: the mean of the squared distance from each point to its nearest map
    point, truncated at `reach` [m] (KISS-ICP's kernel) so that points the map does not see cost the same whatever
    the pose, in units of `reach` squared (0: every point on the map, 1: none near it)."""

    def __init__(self, map_points: np.ndarray, reach: float):
        self.tree = cKDTree(map_points)
        self.reach = reach

    def cost(self, points: np.ndarray, pose: np.ndarray) -> float:
        """Cost of `points` (N, 3) [m] in the sensor frame at `pose` (T_world_sensor)."""
        distances, _ = self.tree.query(points @ pose[:3, :3].T + pose[:3, 3], distance_upper_bound=self.reach)
        return float(np.mean(np.minimum(distances / self.reach, 1.0) ** 2)) if len(points) else np.inf


def best_sweep_rotation(first: tuple[float, Fit], register: Callable[[np.ndarray], tuple[float, Fit]]) -> Fit:
    """The best fit (lowest cost) of `first`, the scan deskewed with the prediction and registered, and of the scan
    deskewed with the prediction's rotation turned further by a rotation vector [rad] in the sensor frame and
    registered (`register(rotation_vector)` -> (cost, fit)): STEP_DEG about each sensor axis both ways, then the
    best of those at half and at twice the angle."""
    (best_cost, best), step = first, None
    for rotation_vector in np.radians(STEP_DEG) * np.array([sign * axis for axis in np.eye(3) for sign in (1, -1)]):
        cost, fit = register(rotation_vector)
        if cost < best_cost:
            best_cost, best, step = cost, fit, rotation_vector
    if step is not None:
        for factor in (0.5, 2.0):
            cost, fit = register(factor * step)
            if cost < best_cost:
                best_cost, best = cost, fit
    return best


def turned(motion: np.ndarray, rotation_vector: np.ndarray) -> np.ndarray:
    """`motion` (4x4, the scan-to-scan motion deskewing takes) with its rotation turned further by
    `rotation_vector` [rad], in the frame of the scan's end."""
    out = motion.copy()
    out[:3, :3] = motion[:3, :3] @ Rotation.from_rotvec(rotation_vector).as_matrix()
    return out
