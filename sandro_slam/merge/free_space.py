"""The free-space test: loops that put one session's surfaces where the other session's rays passed freely."""

from __future__ import annotations

import numpy as np

from sandro_core.geometry import transform_points
from sandro_slam.config import MergeConfig
from sandro_slam.merge.loops import Descriptions, InterSessionLoop


class FreeSpace:
    """Per keyframe (session index, key), computed on first use: the voxels its keypoints' rays crossed
    freely, and its ground plane."""

    def __init__(self, descriptions: Descriptions, voxel: float):
        self.descriptions, self.voxel = descriptions, voxel
        self._cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}

    def get(self, session: int, key: int) -> tuple[np.ndarray, np.ndarray | None]:
        if (session, key) not in self._cache:
            cloud = self.descriptions[session][key].cloud
            self._cache[(session, key)] = free_voxels(np.asarray(cloud.points), np.asarray(cloud.normals), self.voxel)
        return self._cache[(session, key)]


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 per voxel of edge `voxel` [m] (21 bits per axis: +-1e6 voxels)."""
    index = np.floor(points / voxel).astype(np.int64) + (1 << 20)
    return (index[:, 0] << 42) | (index[:, 1] << 21) | index[:, 2]


def ground_plane(points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
    """(a, b, c) of the ground z = a x + b y + c [m] in a keyframe frame (z up, the sensor above the ground),
    fitted to points at least 0.5 m below the sensor with upright normals; None when there are too few."""
    candidates = points[(np.abs(normals[:, 2]) > 0.9) & (points[:, 2] < -0.5)]
    if len(candidates) < 10:
        return None
    A = np.c_[candidates[:, :2], np.ones(len(candidates))]
    plane = np.linalg.lstsq(A, candidates[:, 2], rcond=None)[0]
    for _ in range(2):
        near = np.abs(A @ plane - candidates[:, 2]) < 0.3
        if near.sum() < 3:
            break
        plane = np.linalg.lstsq(A[near], candidates[near, 2], rcond=None)[0]
    return plane


def _above(points: np.ndarray, plane: np.ndarray | None, height: float) -> np.ndarray:
    """Mask of points more than `height` [m] above the ground plane (all, without a plane)."""
    if plane is None:
        return np.ones(len(points), dtype=bool)
    return points[:, 2] - (points[:, :2] @ plane[:2] + plane[2]) > height


def free_voxels(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Voxels (sorted `_voxel_keys`) that rays from the keyframe origin to its points (keyframe frame [m])
    crossed without a return, and the ground plane.

    A ray counts up to `voxel` short of its surface, measured normal to that surface (a grazing ray stops
    early), and only more than `voxel` above the ground; voxels next to any point are never free."""
    distance = np.linalg.norm(points, axis=1)
    keep = distance > voxel
    points, normals, distance = points[keep], normals[keep], distance[keep]
    direction = points / distance[:, None]
    incidence = np.abs(np.sum(direction * normals, axis=1))
    step = 0.5 * voxel
    steps = np.maximum(0, ((distance - voxel / np.maximum(incidence, 0.05)) / step).astype(np.int64))
    ray = np.repeat(np.arange(len(points)), steps)
    along = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps) + 1) * step
    samples = direction[ray] * along[:, None]
    plane = ground_plane(points, normals)
    free = np.unique(_voxel_keys(samples[_above(samples, plane, voxel)], voxel))
    around = voxel * np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    occupied = np.unique(_voxel_keys((points[:, None, :] + around[None]).reshape(-1, 3), voxel))
    return np.setdiff1d(free, occupied, assume_unique=True), plane


def free_space_conflict(
    free: np.ndarray, plane: np.ndarray | None, points: np.ndarray, T_target_source: np.ndarray, voxel: float
) -> tuple[int, int]:
    """(conflicting, tested): of the source `points` more than `voxel` above the target's ground once moved
    by T_target_source, how many lie in the target's `free` voxels (from `free_voxels`)."""
    moved = transform_points(T_target_source, points)
    keys = _voxel_keys(moved[_above(moved, plane, voxel)], voxel)
    at = np.minimum(np.searchsorted(free, keys), max(len(free) - 1, 0))
    hits = int(np.sum(free[at] == keys)) if len(free) else 0
    return hits, len(keys)


def _loop_conflict(loop: InterSessionLoop, descriptions: Descriptions, free: FreeSpace, voxel: float) -> float:
    """The loop's conflict: the share of both submaps' keypoints in the other's free space."""
    hits, tested = 0, 0
    for (i, ki), (j, kj), T in (
        ((loop.target_session, loop.target_key), (loop.source_session, loop.source_key), loop.T_target_source),
        (
            (loop.source_session, loop.source_key),
            (loop.target_session, loop.target_key),
            np.linalg.inv(loop.T_target_source),
        ),
    ):
        h, n = free_space_conflict(*free.get(i, ki), descriptions[j][kj].keypoints, T, voxel)
        hits, tested = hits + h, tested + n
    return hits / tested if tested else 0.0


def pair_conflict(
    voters: list[InterSessionLoop], descriptions: Descriptions, free: FreeSpace, merge: MergeConfig
) -> float:
    """Median conflict of the `conflict_loops` agreeing loops with the most inliers (stored on the loops)."""
    tested = sorted(voters, key=lambda lp: -lp.inliers)[: merge.conflict_loops]
    for loop in tested:
        loop.conflict = _loop_conflict(loop, descriptions, free, merge.free_space_voxel)
    return float(np.median([loop.conflict for loop in tested]))
