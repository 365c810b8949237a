"""A LiDAR scan as every source of frames hands it over: the bag reader, the simulator, the caller's own code."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np


class Scan(NamedTuple):
    """One sweep: `points` (N, 3) [m] in the sensor frame, `times` (N,) [s] per point relative to `timestamp`
    [s], or an empty array when the sweep carries no per-point time (it is then not deskewed).

    A plain tuple `(timestamp, points[, times])` is accepted wherever a Scan is (see `as_scan`).
    """

    timestamp: float
    points: np.ndarray
    times: np.ndarray


def as_scan(frame: Sequence, index: int) -> Scan:
    """`frame` as a Scan of float64 arrays: a Scan or a tuple (timestamp, points[, times or None]).

    Raises:
        ValueError: naming frame `index`, when it has the wrong length, points that are not (N, 3), or a
            number of times other than one per point.
    """
    if len(frame) not in (2, 3):
        raise ValueError(f"frame {index}: expected (timestamp, points[, times]), got {len(frame)} items")
    points = np.asarray(frame[1], dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"frame {index}: points must be an (N, 3) array, got shape {points.shape}")
    times = frame[2] if len(frame) == 3 else None
    if times is None:
        times = np.empty(0)  # KISS-ICP's convention for "no per-point times": no deskewing
    else:
        times = np.asarray(times, dtype=np.float64).ravel()
        if len(times) and len(times) != len(points):  # no times at all is allowed: not deskewed
            raise ValueError(f"frame {index}: {len(times)} per-point times for {len(points)} points")
    return Scan(float(frame[0]), points, times)
