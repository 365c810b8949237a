"""Loop candidates: keyframes near the new one in the current estimate, and place recognition (MapClosures' density
images, ring keys)."""

from __future__ import annotations

import numpy as np

from sandro_slam.config import LoopDetectionConfig


def span_centres(anchors: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The middle [m, world] of the stretch of travel each keyframe's submap covers, from the keyframes'
    anchor positions (`anchors`, in the order the keyframes were added): a submap spans the travel from its
    anchor to the next keyframe's, and the newest keyframe's next anchor, not known yet, is extrapolated from
    its last step."""
    keys = list(anchors)
    centres = {}
    for i, key in enumerate(keys):
        if i + 1 < len(keys):
            centres[key] = 0.5 * (anchors[key] + anchors[keys[i + 1]])
        elif i > 0:
            centres[key] = anchors[key] + 0.5 * (anchors[key] - anchors[keys[i - 1]])
        else:
            centres[key] = anchors[key]
    return centres


def radius_candidates(
    key: int,
    centres: dict[int, np.ndarray],
    travelled: dict[int, float],
    config: LoopDetectionConfig,
    limit: int | None = None,
) -> list[int]:
    """Keyframes whose submaps' span centres (`span_centres`, current estimate) lie within `radius` metres of
    `key`'s, at least `exclude_recent` metres of travel back, nearest first, at most `limit` (None:
    `max_candidates`).

    Centres rather than anchors: on a stretch driven back the other way, the anchor nearest to the new keyframe
    starts a submap over the stretch the new keyframe has not covered yet."""
    here = centres[key]
    near = []
    for other, position in centres.items():
        if other == key or travelled[key] - travelled[other] < config.exclude_recent:
            continue
        distance = float(np.linalg.norm(position - here))
        if distance <= config.radius:
            near.append((distance, other))
    return [other for _, other in sorted(near)[: config.max_candidates if limit is None else limit]]


class PlaceRecognition:
    """MapClosures (density-map ORB matching) over keyframe submaps: finds revisits that drift hides."""

    def __init__(self, config: LoopDetectionConfig):
        self.config = config
        self._closures = None  # MapClosures, made on first use
        self._seen: dict[int, tuple[int, np.ndarray]] = {}  # the submaps it saw by key, with their MapClosures id
        # (references, not copies)
        self._key_of_id: dict[int, int] = {}
        self._last_seen: float | None = None  # path length [m] at the last keyframe MapClosures saw

    def __getstate__(self) -> dict:
        # MapClosures does not pickle: `_detector` rebuilds it from the submaps it saw.
        return {**self.__dict__, "_closures": None}

    def candidates(self, key: int, points: np.ndarray, travelled: dict[int, float]) -> list[int]:
        """Add keyframe `key`'s submap (keyframe frame) and return earlier keyframes that look like it,
        best first, skipping the last `exclude_recent` metres. A keyframe less than `map_closures_spacing` metres
        along the path from the last one added is neither added nor matched: at the defaults every other
        keyframe, whose 60 m wide density maps still overlap by three quarters. `travelled` holds the path length
        at every keyframe added so far, in the order they were added."""
        if self._last_seen is not None and travelled[key] - self._last_seen < self.config.map_closures_spacing:
            return []
        self._last_seen = travelled[key]
        detector = self._detector()
        # MapClosures takes a C int as a map's id, and keys may be any 64-bit gtsam key: the id is the keyframe's
        # position in the order of `travelled` (the key itself when keys count keyframes from 0).
        map_id = len(travelled) - 1 if next(reversed(travelled)) == key else list(travelled).index(key)
        self._seen[key] = (map_id, points)
        self._key_of_id[map_id] = key
        found = []
        for closure in detector.get_closures(map_id, self._density_map_points(points)):
            other_id = closure.target_id if closure.source_id == map_id else closure.source_id
            other = self._key_of_id.get(other_id, key)
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

            self._closures = MapClosures(
                MapClosuresConfig(
                    density_map_resolution=self.config.map_closures_resolution,
                    inliers_threshold=self.config.map_closures_min_inliers,
                )
            )
            for map_id, points in self._seen.values():
                self._closures.get_closures(map_id, self._density_map_points(points))
        return self._closures

    def _density_map_points(self, points: np.ndarray) -> np.ndarray:
        # Cropping the submap for the density map keeps the revisits it finds here at a ninth of the time.
        return points[np.linalg.norm(points[:, :2], axis=1) <= self.config.map_closures_radius]


def ring_key(
    points: np.ndarray,
    radius: float,
    rings: int = 10,
    sectors: int = 60,
    heights: tuple[float, ...] = (-1.0, 1.0, 4.0, 10.0),
) -> np.ndarray:
    """A yaw-invariant place descriptor of a submap (points in the keyframe frame, z up [m]): per height band
    (edges `heights` above the keyframe origin) and ring (up to `radius`), the share of azimuth sectors
    holding a point."""
    r = np.linalg.norm(points[:, :2], axis=1)
    inside = r < radius
    ring = (r[inside] / radius * rings).astype(int)
    sector = ((np.arctan2(points[inside, 1], points[inside, 0]) + np.pi) / (2 * np.pi) * sectors).astype(int)
    band = np.digitize(points[inside, 2], heights)
    occupied = np.zeros((len(heights) + 1, rings, sectors))
    occupied[band, ring, sector % sectors] = 1.0
    return occupied.mean(axis=2).ravel()


class RingKeyRecognition:
    """Earlier keyframes whose submaps have the nearest ring keys: finds revisits that drift hides where
    MapClosures' density images hold too few features (rooms and corridors, narrow fields of view)."""

    def __init__(self, config: LoopDetectionConfig):
        self.config = config
        self._keys: list[int] = []
        self._descriptors: list[np.ndarray] = []

    def candidates(self, key: int, points: np.ndarray, travelled: dict[int, float]) -> list[int]:
        """Add keyframe `key`'s submap (keyframe frame) and return the `ring_key_candidates` earlier keyframes,
        at least `exclude_recent` metres of travel back, with the nearest ring keys, nearest first."""
        descriptor = ring_key(points, self.config.ring_key_radius)
        back = self.config.exclude_recent
        earlier = [i for i, other in enumerate(self._keys) if travelled[key] - travelled[other] >= back]
        self._keys.append(key)
        self._descriptors.append(descriptor)
        if not earlier:
            return []
        distances = np.linalg.norm(np.array([self._descriptors[i] for i in earlier]) - descriptor, axis=1)
        return [self._keys[earlier[i]] for i in np.argsort(distances, kind="stable")[: self.config.ring_key_candidates]]
