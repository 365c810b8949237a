"""A LiDAR scan as every source of frames hands it over: the bag reader, the simulator, the caller's own code."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np
from kiss_icp.voxelization import voxel_down_sample

MIN_VOXEL_SHARE = 0.1  # a scan occupying fewer voxels than this share of the scans before it is skipped
MIN_VOXELS = 100  # and a scan occupying fewer than this, whatever the scans before it held
VOXEL_COUNT_SCANS = 10  # scans whose median voxel count a scan is compared with


class Scan(NamedTuple):
    """One sweep: `points` (N, 3) [m] in the sensor frame, `times` (N,) [s] per point relative to `timestamp`
    [s], or an empty array when the sweep carries no per-point time (it is then not deskewed; times that are all
    the same carry none either, `as_scan`).

    A plain tuple `(timestamp, points[, times])` is accepted wherever a Scan is (see `as_scan`).
    """

    timestamp: float
    points: np.ndarray
    times: np.ndarray


def as_scan(frame: Sequence, index: int) -> Scan:
    """`frame` as a Scan of float64 arrays: a Scan or a tuple (timestamp, points[, times or None]). Times that are
    all the same (one firing of a spinning sensor, a driver that stamps whole packets) become none: KISS-ICP
    normalises them by their span, and a span of zero aborts the process.

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
        if len(times) and not times.max() > times.min():
            times = np.empty(0)
    return Scan(float(frame[0]), points, times)


class SparseScans:
    """Tells the scans that hold too little to register, counted in occupied odometry voxels (`occupied_voxels`):
    fewer than MIN_VOXELS, or than MIN_VOXEL_SHARE of the median of the VOXEL_COUNT_SCANS scans before them (a
    driver's partial first sweep, lost packets, a sensor blocked by a hand). KISS-ICP would register their few
    points anywhere and carry the error on in its map and motion model.

    The scans before are first `first_counts` (the counts of scans read ahead, so that the first scan is judged
    too), then every scan judged, sparse ones included: a scene that stays sparse (above MIN_VOXELS) is taken after
    a few scans.
    """

    def __init__(self, first_counts: Iterable[int] = ()):
        self._counts: deque[int] = deque(first_counts, maxlen=VOXEL_COUNT_SCANS)

    def __call__(self, count: int) -> bool:
        """Whether a scan occupying `count` voxels is sparse; it counts among the scans before the next either way."""
        sparse = count < MIN_VOXELS or (bool(self._counts) and count < MIN_VOXEL_SHARE * np.median(self._counts))
        self._counts.append(count)
        return sparse


def occupied_voxels(points: np.ndarray, voxel: float, min_range: float, max_range: float) -> int:
    """How many voxels of edge `voxel` [m] the (N, 3) points [m] within [min_range, max_range] of the sensor occupy:
    the structure KISS-ICP registers (20 points of one firing: at most 20; a hand over the sensor: a few)."""
    squared = np.einsum("ij,ij->i", points, points)
    used = points[(squared >= min_range**2) & (squared <= max_range**2)]
    return len(voxel_down_sample(used, voxel)) if len(used) else 0
