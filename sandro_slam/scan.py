"""A LiDAR scan as every source of frames hands it over: the bag reader, the simulator, the caller's own code."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

MIN_POINT_SHARE = 0.1  # a scan with fewer points than this share of the scans before it is skipped
POINT_COUNT_SCANS = 10  # scans whose median point count a scan is compared with


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


class SparseScans:
    """Tells the scans that hold too few points to register: fewer than MIN_POINT_SHARE of the median point count
    of the POINT_COUNT_SCANS scans before them (a driver's partial first sweep, lost packets, a blocked sensor).
    KISS-ICP would register their few points anywhere and carry the error on in its map and motion model.

    The scans before are first `first_counts` (the point counts of scans read ahead, so that the first scan is
    judged too), then every scan judged, sparse ones included: a scene that stays that sparse is taken after a
    few scans.
    """

    def __init__(self, first_counts: Iterable[int] = ()):
        self._counts: deque[int] = deque(first_counts, maxlen=POINT_COUNT_SCANS)

    def __call__(self, count: int) -> bool:
        """Whether a scan of `count` points is sparse; it then counts among the scans before the next."""
        sparse = bool(self._counts) and count < MIN_POINT_SHARE * float(np.median(self._counts))
        self._counts.append(count)
        return sparse
