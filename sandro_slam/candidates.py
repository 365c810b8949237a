"""Loop candidates: keyframes near the new one in the current estimate, and place recognition."""

from __future__ import annotations

import numpy as np

from sandro_slam.config import LoopDetectionConfig


def radius_candidates(
    key: int,
    positions: dict[int, np.ndarray],
    travelled: dict[int, float],
    config: LoopDetectionConfig,
) -> list[int]:
    """Keyframes within `radius` metres of `key` in the current estimate, at least `exclude_recent` metres
    of travel back, nearest first, at most `max_candidates`."""
    here = positions[key]
    near = []
    for other, position in positions.items():
        if other == key or travelled[key] - travelled[other] < config.exclude_recent:
            continue
        distance = float(np.linalg.norm(position - here))
        if distance <= config.radius:
            near.append((distance, other))
    return [other for _, other in sorted(near)[: config.max_candidates]]


class PlaceRecognition:
    """MapClosures (density-map ORB matching) over keyframe submaps: finds revisits that drift hides."""

    def __init__(self, config: LoopDetectionConfig):
        from map_closures.config import MapClosuresConfig
        from map_closures.map_closures import MapClosures

        self.config = config
        self._closures = MapClosures(MapClosuresConfig(inliers_threshold=config.map_closures_min_inliers))
        self._last_seen: float | None = None  # path length [m] at the last keyframe MapClosures saw

    def candidates(self, key: int, points: np.ndarray, travelled: dict[int, float]) -> list[int]:
        """Add keyframe `key`'s submap (keyframe frame) and return earlier keyframes that look like it,
        best first, skipping the last `exclude_recent` metres. A keyframe less than `map_closures_spacing` metres
        along the path from the last one added is neither added nor matched: at the defaults every other
        keyframe, whose 60 m wide density maps still overlap by three quarters (simulated drive: the same
        loops, half of MapClosures' time)."""
        if self._last_seen is not None and travelled[key] - self._last_seen < self.config.map_closures_spacing:
            return []
        self._last_seen = travelled[key]
        found = []
        # Cropping the submap for the density map keeps the revisits it finds here at a ninth of the time.
        near = points[np.linalg.norm(points[:, :2], axis=1) <= self.config.map_closures_radius]
        for closure in self._closures.get_closures(key, near):
            other = closure.target_id if closure.source_id == key else closure.source_id
            if other == key or other not in travelled or travelled[key] - travelled[other] < self.config.exclude_recent:
                continue
            if closure.number_of_inliers >= self.config.map_closures_min_inliers:
                found.append((closure.number_of_inliers, other))
        return [other for _, other in sorted(found, reverse=True)[: self.config.max_candidates]]
