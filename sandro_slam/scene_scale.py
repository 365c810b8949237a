"""The length scale of a scene, measured from its first scans: what the configuration's lengths follow."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

REFERENCE_RANGE = 33.0  # [m] the 90th percentile of point ranges in the street-scale scenes of the reference values
SCALE_LIMITS = (0.2, 1.0)  # a room 5x finer than a street at most; never coarser than the reference values
SCANS = 10  # scans the scale is measured on


def scene_scale(scans: Sequence[np.ndarray], min_range: float = 0.0, max_range: float = np.inf) -> float:
    """The scene's scale: the 90th percentile of the point ranges [m] (from the sensor, within [min_range,
    max_range]) of up to the first `SCANS` scans (each (N, 3) in its sensor frame), over REFERENCE_RANGE, clipped to
    SCALE_LIMITS. 1 for streets between buildings, ~0.5 in a parking garage, ~0.2 in an office."""
    ranges = [np.linalg.norm(points, axis=1) for points in scans[:SCANS]]
    ranges = np.concatenate(ranges) if ranges else np.empty(0)
    ranges = ranges[(ranges >= min_range) & (ranges <= max_range)]
    if len(ranges) == 0:
        return SCALE_LIMITS[1]
    return float(np.clip(np.percentile(ranges, 90) / REFERENCE_RANGE, *SCALE_LIMITS))
