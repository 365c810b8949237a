"""Cutting the odometry stream into keyframes, each with a submap in its own frame."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from kiss_icp.voxelization import voxel_down_sample

from sandro_core.geometry import rotation_angle, transform_points
from sandro_slam.config import KeyframeConfig

STEADY_DEG = 0.5  # [deg] a change of rotation between consecutive scans' motions that is always steady
RECENT = 20  # scans whose median change of rotation is steady too (a walker's sway changes it on every scan)
MAX_WAIT = 5  # scans a due keyframe waits for a steady one


@dataclass
class Keyframe:
    """A keyframe: its odometry pose, the scans it spans and its submap (points in the keyframe frame)."""

    key: int
    T_world_keyframe: np.ndarray  # odometry estimate, 4x4
    first_frame: int  # index of the scan that started it
    travelled: float  # odometry path length [m] at the keyframe
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel of edge `voxel` [m] (KISS-ICP's voxelisation: several times faster
    than open3d's on scans)."""
    return voxel_down_sample(points, voxel)


def cropped(points: np.ndarray, radius: float) -> np.ndarray:
    """The points (N, 3) within `radius` [m] of the origin of their frame."""
    return points[np.einsum("ij,ij->i", points, points) <= radius**2]


class KeyframeBuilder:
    """Starts a keyframe every `distance` metres or `angle_deg` degrees of odometry and accumulates the
    scans that follow it, until the next keyframe, into its submap.

    A keyframe's frame is the odometry pose of its first scan, so a loop to it carries that one pose's error. A
    scan whose rotation rate changed within its sweep (the first scan of a sharp turn) is deskewed with the wrong
    rate and registered a degree or more off, an error the scans after it do not share. A due keyframe therefore
    starts on the first steady scan, waiting at most MAX_WAIT scans: one whose rotation from the scan before
    differs from the rotation of the scan before that by less than STEADY_DEG or than the median such change over
    the last RECENT scans (under a walker's sway the rate changes on every scan, and no scan is steadier).

    Each scan is moved into the keyframe frame and cropped to `submap_radius`; when the keyframe closes, one
    voxelisation of them all keeps the first point of every voxel. Scans come voxelised already (`Frontend`
    passes the scan KISS-ICP voxelised for its own map), which keeps the points to move few.
    """

    def __init__(self, config: KeyframeConfig):
        self.config = config
        self._current: Keyframe | None = None
        self._scans: list[np.ndarray] = []  # the current keyframe's scans, in its frame
        self._last_pose: np.ndarray | None = None
        self._last_motion: np.ndarray | None = None
        self._changes: deque[float] = deque(maxlen=RECENT)  # [rad] of the latest scans
        self._waited = 0
        self._travelled = 0.0
        self._next_key = 0

    @property
    def travelled(self) -> float:
        """Odometry path length so far [m]."""
        return self._travelled

    def add_scan(self, frame_index: int, T_world_scan: np.ndarray, points: np.ndarray) -> Keyframe | None:
        """Add a deskewed scan (points in the scan frame) at its odometry pose.

        Returns the keyframe this scan completed, if it started a new one; the scan itself then belongs
        to the new keyframe.
        """
        steady = False
        if self._last_pose is not None:
            motion = np.linalg.inv(self._last_pose) @ T_world_scan
            self._travelled += float(np.linalg.norm(T_world_scan[:3, 3] - self._last_pose[:3, 3]))
            if self._last_motion is not None:
                change = rotation_angle(self._last_motion[:3, :3].T @ motion[:3, :3])
                self._changes.append(change)
                steady = change < max(np.radians(STEADY_DEG), float(np.median(self._changes)))
            self._last_motion = motion
        self._last_pose = T_world_scan

        completed = None
        due = self._current is None or self._waited > 0 or self._is_new_keyframe(T_world_scan)
        if due and (self._current is None or steady or self._waited >= MAX_WAIT):
            self._waited = 0
            completed = self.flush()
            self._current = Keyframe(self._next_key, T_world_scan.copy(), frame_index, self._travelled)
            self._next_key += 1
        elif due:
            self._waited += 1
        T_keyframe_scan = np.linalg.inv(self._current.T_world_keyframe) @ T_world_scan
        moved = transform_points(T_keyframe_scan, points)
        self._scans.append(cropped(moved, self.config.submap_radius))
        return completed

    def flush(self) -> Keyframe | None:
        """Close the current keyframe and return it (None if there is none)."""
        keyframe = self._current
        if keyframe is None:
            return None
        keyframe.points = voxel_downsample(np.concatenate(self._scans), self.config.submap_voxel)
        self._current = None
        self._scans = []
        return keyframe

    def current_key(self) -> int | None:
        """Key of the keyframe the latest scan belongs to."""
        return None if self._current is None else self._current.key

    def _is_new_keyframe(self, T_world_scan: np.ndarray) -> bool:
        T_keyframe_scan = np.linalg.inv(self._current.T_world_keyframe) @ T_world_scan
        moved = self._travelled - self._current.travelled
        turned = np.degrees(rotation_angle(T_keyframe_scan[:3, :3]))
        return moved >= self.config.distance or turned >= self.config.angle_deg
