"""The second pass of an offline run: every scan deskewed again and registered onto the loop-corrected map, the
submaps made again from the refined scans, the loops measured again on them, the graph optimised again.

Loop closure moves keyframes as rigid wholes, so what the odometry got wrong inside a keyframe (a sharp turn, a
bad start) stays, in the poses and in the submaps the loops were measured on. After the first pass the keyframe
submaps, at their optimised poses, make a map that is right at the scale of the whole drive; registering each scan
onto it, in order, with the motion between its refined neighbours for deskewing, corrects the poses inside the
keyframes too.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import numpy as np
import small_gicp
from kiss_icp.kiss_icp import KissICP

from sandro_core.geometry import transform_points
from sandro_slam.config import KeyframeConfig, SlamConfig
from sandro_slam.factors import odometry_covariance
from sandro_slam.keyframes import Keyframe, keyframe_frame, submap_points
from sandro_slam.loop_registration import icp_registration
from sandro_slam.module import LoopClosure
from sandro_slam.odometry import GaussianMapRefiner, deskew_to_middle
from sandro_slam.pose_graph import PoseGraph
from sandro_slam.scan import Scan
from sandro_slam.sway import SWAY_DEG, sway_deg

REDESKEW_SHIFT = 0.05  # [m at scale 1] deskew and register again when the registration moves a scan's motion more
DISTINCT_GUESS = 0.5  # [m at scale 1] a scan is registered from more than one start where they lie this far apart,
# and the one with the most points matched is kept


def refine_poses(
    scans: Iterable[Scan],
    poses: np.ndarray,
    keyframes: list[Keyframe],
    keyframe_poses: dict[int, np.ndarray],
    config: SlamConfig,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """The scans' poses after a second pass, (F, 4, 4) T_world_sensor, and the scans deskewed with them (each in
    its sensor frame, voxelised as KISS-ICP does for its map).

    Args:
        scans: the F scans of the first pass, in order (the ones it used: finite points, skipped ones left out).
        poses: (F, 4, 4) their first-pass poses (each moved with its keyframe), at the times the first pass gave.
        keyframes, keyframe_poses: the first pass's keyframes and their optimised T_world_keyframe: the map.
        config: the resolved configuration of the first pass (its odometry settings deskew and voxelise the scans,
            its `odometry_gicp` settings register them, as the odometry's `GaussianMapRefiner`).

    Each scan is deskewed with the motion from the refined pose before it to its own guess (into its frame at the
    middle of the sweep, as in the first pass: `odometry.deskew_to_middle`) and registered with VGICP onto a map of
    Gaussian voxels of the submaps at their optimised poses, from the first-pass pose moved with the correction of
    the scan before; where the first pass's motion jumps, from the other starts of `_guesses` too, keeping the
    registration that matched the most points. When that moved its motion by more than REDESKEW_SHIFT x scale (and
    less than DISTINCT_GUESS x scale: farther, the pose may be a restart from the first pass's, and its motion from
    the scan before no motion the sensor made), it is deskewed with the new motion and registered once more. Scans
    without per-point times are registered as they are. Gaussian voxels, not KISS-ICP's points: the submaps hold one
    point per submap voxel, and point-to-point ICP onto so sparse a map is pulled by the sampling.
    """
    odometry = KissICP(config.odometry)
    world_map = GaussianMapRefiner(config.odometry_gicp)
    submaps = np.concatenate([transform_points(keyframe_poses[kf.key], kf.points) for kf in keyframes])
    world_map.insert(world_map.prepared(submaps), np.eye(4))

    def deskewed(scan: Scan, motion: np.ndarray) -> tuple[np.ndarray, small_gicp.PointCloud]:
        points = deskew_to_middle(odometry.preprocessor, scan.points, scan.times, motion, config.odometry.data.deskew)
        _, fine = odometry.voxelize(points)
        return fine, world_map.prepared(fine)

    refined, deskewed_scans = np.empty_like(poses), []
    for i, scan in enumerate(scans):
        if i >= len(poses):
            raise ValueError(f"more scans than the {len(poses)} poses of the first pass")
        motion = _first_pass_motion(poses, i)  # from the refined scan before to this one's guess
        guesses = [(poses[0], motion)] if i == 0 else _guesses(refined[:i], poses[i], motion, config)
        prepared = {}  # per motion: guesses may share one
        for _, start in guesses:
            if start.tobytes() not in prepared:
                prepared[start.tobytes()] = deskewed(scan, start)
        pose, _, start = max(
            (world_map.register(prepared[start.tobytes()][1], guess) + (start,) for guess, start in guesses),
            key=lambda candidate: candidate[1],
        )
        fine = prepared[start.tobytes()][0]
        if i > 0:
            moved = np.linalg.inv(refined[i - 1]) @ pose
            shift = np.linalg.norm(moved[:3, 3] - start[:3, 3])
            if len(scan.times) and REDESKEW_SHIFT * config.scale <= shift < DISTINCT_GUESS * config.scale:
                fine, cloud = deskewed(scan, moved)
                pose, _ = world_map.register(cloud, pose)
        refined[i] = pose
        deskewed_scans.append(fine)
    if len(deskewed_scans) != len(poses):
        raise ValueError(f"{len(deskewed_scans)} scans for the {len(poses)} poses of the first pass")
    return refined, deskewed_scans


def rebuilt_keyframes(
    keyframes: list[Keyframe],
    keyframe_of_frame: np.ndarray,
    poses: np.ndarray,
    scans: list[np.ndarray],
    config: KeyframeConfig,
) -> list[Keyframe]:
    """The keyframes made again from refined scans: the same scans each, the frame of each from the refined poses
    of its anchor and its scans (`keyframe_frame`), its submap from the scans (sensor frame) at their refined
    `poses`, cropped and voxelised as the first pass does it."""
    rebuilt = []
    for keyframe in keyframes:
        frames = np.flatnonzero(keyframe_of_frame == keyframe.key)
        T_world_keyframe = keyframe_frame(poses[keyframe.anchor_frame], poses[frames])
        points = submap_points(T_world_keyframe, [poses[i] for i in frames], [scans[i] for i in frames], config)
        rebuilt.append(
            Keyframe(keyframe.key, T_world_keyframe.copy(), keyframe.anchor_frame, keyframe.travelled, points)
        )
    return rebuilt


def reoptimized(
    keyframes: list[Keyframe], loops: list[LoopClosure], config: SlamConfig, estimate_odometry_noise: bool
) -> tuple[PoseGraph, list[LoopClosure], dict[int, np.ndarray]]:
    """The keyframe graph made again: odometry between consecutive rebuilt keyframes, each loop the first pass kept
    measured again by ICP between the rebuilt submaps from their refined relative pose (kept as it was when that
    ICP does not reach `min_overlap`), the others as they were; robustly optimised. (graph, the loops in it,
    T_world_keyframe per key.)"""
    graph = PoseGraph(config.graph)
    by_key = {keyframe.key: keyframe for keyframe in keyframes}
    previous = None
    for keyframe in keyframes:
        if previous is None:
            graph.add_pose(keyframe.key, keyframe.T_world_keyframe)
        else:
            distance = float(np.linalg.norm(keyframe.T_world_keyframe[:3, 3] - previous.T_world_keyframe[:3, 3]))
            covariance = odometry_covariance(distance, config.graph)
            graph.add_pose(keyframe.key, keyframe.T_world_keyframe, previous.key, covariance)
        previous = keyframe
    measured = []
    for loop in loops:
        T = loop.T_target_source
        if loop.weight >= 0.5:
            target, source = by_key[loop.target_key], by_key[loop.source_key]
            guess = np.linalg.inv(target.T_world_keyframe) @ source.T_world_keyframe
            icp, overlap = icp_registration(target.points, source.points, guess, config.registration)
            if overlap >= config.registration.min_overlap:
                T = icp
        factor = graph.add_loop(loop.target_key, loop.source_key, T, loop.covariance)
        measured.append(replace(loop, T_target_source=T, factor=factor))
    return graph, measured, graph.optimize(estimate_odometry_noise)


def pays(setting: bool | str, odometry_poses: np.ndarray) -> bool:
    """Whether the second pass runs: `setting` (the configuration's `refine`) where it is a bool; for "auto", where
    the odometry's poses (F, 4, 4) sway (`sway_deg` above SWAY_DEG; on a car's steady motion the pass costs
    accuracy, docs/benchmarks.md)."""
    return setting if isinstance(setting, bool) else sway_deg(odometry_poses) > SWAY_DEG


def _guesses(
    refined: np.ndarray, first_pass_pose: np.ndarray, motion: np.ndarray, config: SlamConfig
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where to start registering scan i (T_world_sensor) and the motion to deskew it with (T_previous_current), given
    the refined poses before it (`refined`, i >= 1 of them), its first-pass pose and the first pass's motion over it.

    The refined scan before moved by the first pass's motion, first; where the odometry lost its way the first
    pass's motion jumps, so also, where they differ by more than DISTINCT_GUESS x scale: that scan moved by the
    refined motion over it (constant velocity), and the first-pass pose itself (so that one scan gone wrong does not
    carry into all after it)."""
    distinct = DISTINCT_GUESS * config.scale
    previous = refined[-1]
    guesses = [(previous @ motion, motion)]
    if len(refined) > 1:
        velocity = np.linalg.inv(refined[-2]) @ previous
        if np.linalg.norm(velocity[:3, 3] - motion[:3, 3]) > distinct:
            guesses.append((previous @ velocity, velocity))
    if np.linalg.norm(first_pass_pose[:3, 3] - guesses[0][0][:3, 3]) > distinct:
        guesses.append((first_pass_pose, motion))
    return guesses


def _first_pass_motion(poses: np.ndarray, i: int) -> np.ndarray:
    """The first pass's motion over scan i, T_previous_current (the first scan: the motion to the next)."""
    if i == 0:
        return np.linalg.inv(poses[0]) @ poses[1] if len(poses) > 1 else np.eye(4)
    return np.linalg.inv(poses[i - 1]) @ poses[i]
