"""Per-point times from the azimuth for raw sweeps of a spinning LiDAR that come without them (`sweep_times`).

A driver that leaves the time field out hands over either raw sweeps (every point where the sensor was when it
fired: smeared by the motion over the sweep) or clouds a LiDAR-inertial front end deskewed, and nothing in one cloud
tells which: clouds without time are taken as deskewed unless the configuration names the sensor's turning
direction. Then each point gets the time at which a sensor turning that way, once per sweep, starting looking
backwards, looks in its direction, and KISS-ICP deskews the sweep with it (docs/benchmarks.md, "Raw sweeps without
time"). Not for a swaying sensor (a walker, a hand): deskewing at the constant velocity of the sweep before adds
the sway instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from sandro_slam.scan import Scan

Rotation = Literal["clockwise", "counterclockwise"]


def azimuth_times(points: np.ndarray, period: float, rotation: Rotation) -> np.ndarray:
    """(N,) per-point times [s] of a spinning sensor's sweep for `points` (N, 3) in the sensor frame: the sweep starts
    looking backwards (azimuth pi, KISS-ICP's KITTI convention) and turns once in `period` [s], `rotation` seen from
    above."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    turned = np.pi - azimuth if rotation == "clockwise" else azimuth + np.pi
    return np.mod(turned / (2.0 * np.pi), 1.0) * period


def with_azimuth_times(scan: Scan, period: float, rotation: Rotation | None) -> Scan:
    """`scan` with `azimuth_times` where it has no per-point times and `rotation` is set; else as it is."""
    if rotation is None or len(scan.times) or not len(scan.points):
        return scan
    return Scan(scan.timestamp, scan.points, azimuth_times(scan.points, period, rotation))


def sweep_period(stamps: Sequence[float]) -> float:
    """The median spacing [s] of consecutive scan stamps: one turn of the sensor (0.1 s with fewer than two)."""
    steps = np.diff(np.asarray(stamps, dtype=np.float64))
    steps = steps[steps > 0.0]
    return float(np.median(steps)) if len(steps) else 0.1
