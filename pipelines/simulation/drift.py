"""Odometry with the drift of a LiDAR-inertial front end, made from the true poses, for given-odometry runs."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

DRIFT_TURN = 300.0  # [m] of travel in which the direction of the position drift turns once
DRIFT_CLIMB = 0.5  # the drift direction's vertical component, against 1 horizontally
HEADING_DRIFT_PER_RATE = 1e-3  # [rad/m] of heading drift per unit of position drift rate


def drifted(poses: np.ndarray, rate: float) -> np.ndarray:
    """(N, 4, 4) odometry from (N, 4, 4) true poses T_world_sensor, drifting by `rate` of the distance travelled
    (0.005: 0.5 %): every step's translation is off by `rate` of its length along a direction that turns slowly
    (once per `DRIFT_TURN` metres, climbing as well), and the heading drifts by `rate` x `HEADING_DRIFT_PER_RATE`
    rad per metre. Roll and pitch do not drift (gravity holds them in a LiDAR-inertial front end)."""
    steps = np.diff(poses[:, :3, 3], axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(lengths)])
    angle = 2.0 * np.pi * travelled[1:] / DRIFT_TURN
    direction = np.column_stack([np.cos(angle), np.sin(angle), np.full_like(angle, DRIFT_CLIMB)])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    heading = Rotation.from_euler("z", rate * HEADING_DRIFT_PER_RATE * travelled[:, None]).as_matrix()
    out = poses.copy()
    out[:, :3, :3] = heading @ poses[:, :3, :3]
    moves = np.einsum("nij,nj->ni", heading[1:], steps) + rate * lengths[:, None] * direction
    out[:, :3, 3] = poses[0, :3, 3] + np.concatenate([np.zeros((1, 3)), np.cumsum(moves, axis=0)])
    return out
