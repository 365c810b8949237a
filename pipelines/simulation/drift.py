"""Odometry with the drift of a LiDAR-inertial front end, made from the true poses, for given-odometry runs."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

DRIFT_TURN = 300.0  # [m] of travel in which the direction of the position drift turns once
DRIFT_CLIMB = 0.5  # the drift direction's vertical component, against 1 horizontally
HEADING_DRIFT_PER_RATE = 1e-3  # [rad/m] of heading drift per unit of position drift rate


def drifted(poses: np.ndarray, rate: float) -> np.ndarray:
    """(N, 4, 4) odometry from (N, 4, 4) true poses T_world_sensor, drifting by `rate` of the distance travelled:
    `Drift` over all of them."""
    drift = Drift(rate)
    return np.array([drift(pose) for pose in poses])


class Drift:
    """Odometry made from true poses T_world_sensor one at a time, in order (a drive streamed), drifting by `rate`
    of the distance travelled (0.005: 0.5 %): every step's translation is off by `rate` of its length along a
    direction that turns slowly (once per `DRIFT_TURN` metres, climbing as well), and the heading drifts by
    `rate` x `HEADING_DRIFT_PER_RATE` rad per metre. Roll and pitch do not drift (gravity holds them in a
    LiDAR-inertial front end)."""

    def __init__(self, rate: float):
        self.rate = rate
        self._last: np.ndarray | None = None  # the last true position
        self._start = np.zeros(3)
        self._moved = np.zeros(3)  # the drifted steps summed, from the first position
        self._travelled = 0.0

    def __call__(self, pose: np.ndarray) -> np.ndarray:
        """The odometry (4x4) of the next true pose (4x4)."""
        position = np.asarray(pose, dtype=np.float64)[:3, 3]
        if self._last is None:
            self._start = position.copy()
        else:
            step = position - self._last
            length = float(np.linalg.norm(step))
            self._travelled += length
            angle = 2.0 * np.pi * self._travelled / DRIFT_TURN
            direction = np.array([np.cos(angle), np.sin(angle), DRIFT_CLIMB])
            direction /= np.linalg.norm(direction)
            self._moved = self._moved + (self._heading() @ step + self.rate * length * direction)
        self._last = position.copy()
        out = np.array(pose, dtype=np.float64)
        out[:3, :3] = self._heading() @ out[:3, :3]
        out[:3, 3] = self._start + self._moved
        return out

    def _heading(self) -> np.ndarray:
        return Rotation.from_euler("z", self.rate * HEADING_DRIFT_PER_RATE * self._travelled).as_matrix()
