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
        self.config = config
        self._closures = None  # MapClosures, made on first use
        self._seen: dict[int, np.ndarray] = {}  # the submaps it saw, by key: references, not copies
        self._last_seen: float | None = None  # path length [m] at the last keyframe MapClosures saw

    def __getstate__(self) -> dict:
        # MapClosures does not pickle: `_detector` rebuilds it from the submaps it saw.
        return {**self.__dict__, "_closures": None}

    def candidates(self, key: int, points: np.ndarray, travelled: dict[int, float]) -> list[int]:
        """Add keyframe `key`'s submap (keyframe frame) and return earlier keyframes that look like it,
        best first, skipping the last `exclude_recent` metres. A keyframe less than `map_closures_spacing` metres
        along the path from the last one added is neither added nor matched: at the defaults every other
        keyframe, whose 60 m wide density maps still overlap by three quarters."""
        if self._last_seen is not None and travelled[key] - self._last_seen < self.config.map_closures_spacing:
            return []
        self._last_seen = travelled[key]
        detector = self._detector()
        self._seen[key] = points
        found = []
        for closure in detector.get_closures(key, self._density_map_points(points)):
            other = closure.target_id if closure.source_id == key else closure.source_id
            if other == key or other not in travelled or travelled[key] - travelled[other] < self.config.exclude_recent:
                continue
            if closure.number_of_inliers >= self.config.map_closures_min_inliers:
                found.append((closure.number_of_inliers, other))
        return [other for _, other in sorted(found, reverse=True)[: self.config.max_candidates]]

    def _detector(self):
        """MapClosures, with the density maps of every submap seen so far (after unpickling: rebuilt)."""
        if self._closures is None:
            from map_closures.config import MapClosuresConfig
            from map_closures.map_closures import MapClosures

            self._closures = MapClosures(MapClosuresConfig(inliers_threshold=self.config.map_closures_min_inliers))
            for key, points in self._seen.items():
                self._closures.get_closures(key, self._density_map_points(points))
        return self._closures

    def _density_map_points(self, points: np.ndarray) -> np.ndarray:
        # Cropping the submap for the density map keeps the revisits it finds here at a ninth of the time.
        return points[np.linalg.norm(points[:, :2], axis=1) <= self.config.map_closures_radius]
