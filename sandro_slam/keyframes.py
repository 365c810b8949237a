"""Cutting the odometry stream into keyframes, each with a submap in its own frame."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial.transform import Rotation

from sandro_core.geometry import rotation_angle, transform_points
from sandro_slam.config import KeyframeConfig

STEADY_DEG = 0.5  # [deg] a change of rotation between consecutive scans' motions that is always steady
RECENT = 20  # scans whose changes of rotation set a steady one too: the walker's sway changes it on every scan
STEADY_QUANTILE = 75  # [%] of those changes: a scan steady on both sides is then about every other one under sway
ANCHOR_SCANS = 6  # a keyframe's frame lies at the position of one of its first this many scans
FOLD_SCANS = 100  # a keyframe holding this many scans' points folds them into its submap (a standstill's bound)
FRAME_SCANS = 100  # a keyframe frame's rotation is the mean over its first this many scans (<= FOLD_SCANS: the
# frame is fixed at the first fold)


@dataclass
class Keyframe:
    """A keyframe: its odometry pose, the scans it spans and its submap (points in the keyframe frame)."""

    key: int
    T_world_keyframe: np.ndarray  # odometry estimate, 4x4 (`keyframe_frame`)
    anchor_frame: int  # index of the scan at whose position the keyframe frame lies (one of its first ANCHOR_SCANS)
    travelled: float  # odometry path length [m] at that scan
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))


class _HeldScan(NamedTuple):
    """A scan of the current keyframe, held until it closes (copied out of the caller's arrays)."""

    frame_index: int
    T_world_scan: np.ndarray
    points: np.ndarray  # in the scan frame
    travelled: float  # [m] odometry path length at the scan
    change: float  # [rad] change of rotation from the motion before to the scan's own (inf: unknown)


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel of edge `voxel` [m] (KISS-ICP's voxelisation: several times faster
    than open3d's on scans)."""
    return voxel_down_sample(points, voxel)


def cropped(points: np.ndarray, radius: float) -> np.ndarray:
    """The points (N, 3) within `radius` [m] of the origin of their frame."""
    return points[np.einsum("ij,ij->i", points, points) <= radius**2]


def keyframe_frame(T_world_anchor: np.ndarray, T_world_scans: np.ndarray) -> np.ndarray:
    """A keyframe's frame (T_world_keyframe, 4x4): at the anchor scan's position, turned to the mean rotation
    (chordal) of the keyframe's first FRAME_SCANS scans (`T_world_scans` (N, 4, 4), its scans in order). A
    keyframe's submap holds the points of all its scans, so the rotation that places it best is theirs on average,
    not one scan's: under a walker's sway each scan's registered rotation is off by a degree, noise that the mean
    of a keyframe's scans averages out and its anchor scan alone would hand to every loop to it."""
    T = np.array(T_world_anchor, dtype=np.float64)
    T[:3, :3] = Rotation.from_matrix(np.asarray(T_world_scans)[:FRAME_SCANS, :3, :3]).mean().as_matrix()
    return T


def keyframe_frames(anchors: dict[int, int], keyframe_of_frame: np.ndarray, poses: np.ndarray) -> dict[int, np.ndarray]:
    """Per key, its keyframe frame (`keyframe_frame`) from the poses (F, 4, 4) of every scan: `anchors` the anchor
    scan's index per key, `keyframe_of_frame` (F,) each scan's key. From the odometry's poses the frames the builder
    made; from the true poses, their truth."""
    keyframe_of_frame = np.asarray(keyframe_of_frame)
    return {key: keyframe_frame(poses[anchor], poses[keyframe_of_frame == key]) for key, anchor in anchors.items()}


def submap_points(
    T_world_keyframe: np.ndarray,
    T_world_scans: list[np.ndarray],
    scans: list[np.ndarray],
    config: KeyframeConfig,
    folded: np.ndarray | None = None,
) -> np.ndarray:
    """A keyframe's submap [m, keyframe frame]: every scan (N_i, 3) [m, sensor frame], moved by its T_world_scan
    into the keyframe frame and cropped to `submap_radius`, all voxelised at `submap_voxel`. `folded`: the submap
    of the keyframe's earlier scans, whose voxels keep their points (the first point of a voxel stays)."""
    T_keyframe_world = np.linalg.inv(T_world_keyframe)
    moved = [
        cropped(transform_points(T_keyframe_world @ T_world_scan, points), config.submap_radius)
        for T_world_scan, points in zip(T_world_scans, scans)
    ]
    return voxel_downsample(
        np.concatenate([np.empty((0, 3)) if folded is None else folded, *moved]), config.submap_voxel
    )


class KeyframeBuilder:
    """Starts a keyframe every `distance` metres or `angle_deg` degrees of odometry and accumulates the
    scans that follow it, until the next keyframe, into its submap.

    A keyframe's frame lies at the odometry position of one of its scans (its anchor), turned to the mean rotation
    of its scans (`keyframe_frame`). A scan in whose sweep the rotation rate stepped (into or out of a sharp turn)
    is deskewed with the wrong rate and registered off, an error the scans around it do not share; the motions to
    it and from it show it: they differ from their neighbours'. The anchor is the first of the keyframe's first
    ANCHOR_SCANS scans that is steady on both sides: the change of rotation from the motion before it to its own,
    and from its own to the next one's, is below STEADY_DEG or the STEADY_QUANTILE percentile of the changes over the
    last RECENT scans (under a walker's sway the rate changes on every scan, and no scan is steadier); without
    one, the scan of the smallest such change.

    The scans are moved into the keyframe frame and cropped to `submap_radius` when the keyframe closes; one
    voxelisation of them all keeps the first point of every voxel. Scans come voxelised already (`Frontend`
    passes the scan KISS-ICP voxelised for its own map), which keeps the points to move few. A keyframe that
    holds FOLD_SCANS scans' points (the sensor standing still: a car at a light, a robot parked while the recording
    goes on) fixes its anchor and frame and folds them into its submap, which then grows only by what new scans add: the
    same points as one voxelisation at the end, in bounded memory.
    """

    def __init__(self, config: KeyframeConfig):
        self.config = config
        self._key: int | None = None  # the current keyframe's
        self._scans: list[_HeldScan] = []  # the current keyframe's; the points of folded ones dropped
        self._held = 0  # of those scans, how many still hold their points
        self._folded: np.ndarray | None = None  # the submap of the folded scans, in the fixed keyframe frame
        self._anchor_index: int | None = None  # fixed at the first fold
        self._frame: np.ndarray | None = None  # T_world_keyframe, fixed at the first fold
        self._changes: deque[float] = deque(maxlen=RECENT)  # [rad] of the latest scans
        self._last_pose: np.ndarray | None = None
        self._last_motion: np.ndarray | None = None
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
        T_world_scan = T_world_scan.copy()
        change = np.inf  # of rotation from the motion before to this scan's: unknown for the first two scans
        if self._last_pose is not None:
            self._travelled += float(np.linalg.norm(T_world_scan[:3, 3] - self._last_pose[:3, 3]))
            motion = np.linalg.inv(self._last_pose) @ T_world_scan
            if self._last_motion is not None:
                change = rotation_angle(self._last_motion[:3, :3].T @ motion[:3, :3])
                self._changes.append(change)
            self._last_motion = motion
        self._last_pose = T_world_scan

        completed = None
        if self._key is None or self._is_new_keyframe(T_world_scan):
            completed = self._close(change)
            self._key = self._next_key
            self._next_key += 1
        self._scans.append(
            _HeldScan(frame_index, T_world_scan, np.array(points, dtype=np.float64), self._travelled, change)
        )
        self._held += 1
        if self._held >= FOLD_SCANS:
            self._fold()
        return completed

    def flush(self) -> Keyframe | None:
        """Close the current keyframe and return it (None if there is none)."""
        return self._close(np.inf)

    def current_key(self) -> int | None:
        """Key of the keyframe the latest scan belongs to."""
        return self._key

    def _close(self, next_change: float) -> Keyframe | None:
        """The current keyframe, closed; `next_change`: the change of rotation [rad] at the scan after its last."""
        if self._key is None:
            return None
        if self._anchor_index is None:
            self._fix_frame(next_change)
        anchor = self._scans[self._anchor_index]
        keyframe = Keyframe(self._key, self._frame, anchor.frame_index, anchor.travelled, self._submap())
        self._key, self._scans, self._held, self._folded = None, [], 0, None
        self._anchor_index, self._frame = None, None
        return keyframe

    def _fix_frame(self, next_change: float) -> None:
        """Choose the anchor among the scans so far and fix the keyframe frame (`keyframe_frame`)."""
        self._anchor_index = self._anchor(next_change)
        T_world_scans = np.array([scan.T_world_scan for scan in self._scans])
        self._frame = keyframe_frame(self._scans[self._anchor_index].T_world_scan, T_world_scans)

    def _fold(self) -> None:
        """Fix the anchor and frame and fold the points of the scans held into the submap (see the class
        docstring)."""
        if self._anchor_index is None:
            self._fix_frame(np.inf)  # with FOLD_SCANS > ANCHOR_SCANS the scan after the anchor is known
        self._folded = self._submap()
        first_held = len(self._scans) - self._held
        self._scans[first_held:] = [scan._replace(points=np.empty((0, 3))) for scan in self._scans[first_held:]]
        self._held = 0

    def _submap(self) -> np.ndarray:
        """The submap [m, the keyframe frame] of the folded scans and of the scans held (the latest ones)."""
        held = self._scans[len(self._scans) - self._held :]
        return submap_points(
            self._frame, [scan.T_world_scan for scan in held], [scan.points for scan in held], self.config,
            self._folded,
        )  # fmt: skip

    def _anchor(self, next_change: float) -> int:
        """Index into the current scans of the keyframe's anchor (see the class docstring)."""
        changes = [scan.change for scan in self._scans] + [next_change]
        both = np.maximum(changes[:-1], changes[1:])[:ANCHOR_SCANS]
        steady = max(
            np.radians(STEADY_DEG), float(np.percentile(self._changes, STEADY_QUANTILE)) if self._changes else 0.0
        )
        below = np.flatnonzero(both < steady)
        return int(below[0]) if len(below) else int(np.argmin(both))

    def _is_new_keyframe(self, T_world_scan: np.ndarray) -> bool:
        first = self._scans[0]
        moved = self._travelled - first.travelled
        turned = np.degrees(rotation_angle(first.T_world_scan[:3, :3].T @ T_world_scan[:3, :3]))
        return moved >= self.config.distance or turned >= self.config.angle_deg
