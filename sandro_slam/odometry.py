"""KISS-ICP odometry as the SLAM front end uses it, and the re-registration of a run's first scans."""

from __future__ import annotations

import numpy as np
from kiss_icp.kiss_icp import KissICP
from kiss_icp.mapping import get_voxel_hash_map

from sandro_core.geometry import transform_points


class ScanOdometry(KissICP):
    """KISS-ICP that keeps the deskewed scan it voxelised for its map (`map_points`, at half its voxel size, in
    the scan frame): the keyframe submaps take it rather than voxelising the scan again."""

    def voxelize(self, iframe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        source, self.map_points = super().voxelize(iframe)
        return source, self.map_points


def path_length(poses: np.ndarray) -> np.ndarray:
    """(F,) path length [m] travelled at each of the (F, 4, 4) poses."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])


def reregister_start(odometry: KissICP, poses: np.ndarray, scans: list[np.ndarray], distance: float) -> np.ndarray:
    """The first scans' poses (F, 4, 4), re-registered: each scan of the first `distance` metres aligned, from
    the last back to the first, onto a map of the scans after them, with KISS-ICP's own registration; returned
    relative to the first scan again. `scans` are the deskewed scans at `poses`, voxelised no coarser than
    KISS-ICP voxelises them for its map.

    Starting from rest, KISS-ICP fills its map with the ground rings of near-identical scans, and the rings of
    the next scans lock onto them: where little else pins the motion along a street, the odometry stays behind
    while the vehicle speeds up, an error every later pose keeps and no loop removes (those scans move rigidly
    with the first keyframe). The scans of the next `distance` metres, taken in motion, make a map without that
    pattern.
    """
    first = int(np.searchsorted(path_length(poses), distance))  # the first scan of the map
    if first >= len(poses):
        return poses
    local_map = get_voxel_hash_map(odometry.config)
    for pose, scan in zip(poses[first:], scans[first:]):
        local_map.add_points(transform_points(pose, odometry.voxelize(scan)[1]))
    sigma = odometry.adaptive_threshold.get_threshold()
    fixed = poses.copy()
    for i in range(first - 1, -1, -1):
        guess = fixed[i + 1] @ np.linalg.inv(poses[i + 1]) @ poses[i]
        fixed[i] = odometry.registration.align_points_to_map(
            odometry.voxelize(scans[i])[0], local_map, guess, 3.0 * sigma, sigma
        )
    return np.linalg.inv(fixed[0]) @ fixed
