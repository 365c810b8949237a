"""The length scale of a scene, measured from its first scans: what the configuration's lengths follow."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

REFERENCE_RANGE = 33.0  # [m] the 90th percentile of point ranges in the street-scale scenes of the reference values
SCALE_LIMITS = (0.2, 1.0)  # a room 5x finer than a street at most; never coarser than the reference values
SCANS = 100  # scans the scale is measured on: 10 s at 10 Hz, past the one place where a drive starts


def scene_scale(scans: Sequence[np.ndarray], min_range: float = 0.0, max_range: float = np.inf) -> float:
    """The scene's scale: the median over up to the first `SCANS` scans (each (N, 3) in its sensor frame) of each
    scan's 90th percentile of point ranges [m] (from the sensor, within [min_range, max_range]), over
    REFERENCE_RANGE, clipped to SCALE_LIMITS. 1 for streets between buildings, ~0.5 in a parking garage, ~0.2 in
    an office. Over 10 s of scans rather than the first place alone: a drive that starts in a narrow street
    (the 90th percentile there 20 m, 32 m over the drive) is not taken for a garage."""
    percentiles = []
    for points in scans[:SCANS]:
        ranges = np.linalg.norm(points, axis=1)
        ranges = ranges[(ranges >= min_range) & (ranges <= max_range)]
        if len(ranges):
            percentiles.append(np.percentile(ranges, 90))
    if not percentiles:
        return SCALE_LIMITS[1]
    return float(np.clip(np.median(percentiles) / REFERENCE_RANGE, *SCALE_LIMITS))
