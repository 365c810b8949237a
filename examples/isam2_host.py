"""A host that owns its gtsam graph and takes SANDRO's loops: ISAM2 with odometry and GPS-like factors on keys of its
own (gtsam symbols x0, x1, ...), a `LoopCloser` proposing verified loops as ready-to-add factors, and the robust
check run on the host's graph at the end.

The data is simulated (the project's city drive): the host's odometry is the true motion drifting by 0.5 % of the
distance, its keyframe clouds the deskewed scans of each 10 m, and a GPS-like position fix (0.5 m noise) comes every
200 m. Run it: `.venv/bin/python examples/isam2_host.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from pipelines.simulation import simulate_sequence
from pipelines.simulation.drift import drifted
from sandro_slam import LoopCloser, LoopClosure, SlamConfig, check_loops
from sandro_slam.keyframes import KeyframeBuilder, keyframe_frames

GPS_EVERY = 20  # keyframes (200 m)
GPS_SIGMA = 0.5  # [m]


@dataclass
class HostRun:
    """What the host ends with."""

    keys: list[int]  # its keys, in order
    truth: dict[int, np.ndarray]  # the true T_world_keyframe per key
    odometry: dict[int, np.ndarray]  # its odometry per key
    estimate: gtsam.Values  # ISAM2's estimate with the loops it kept
    loops: list[LoopClosure]  # every loop the LoopCloser proposed
    kept: np.ndarray  # per loop: kept by the robust check


def keyframes(frames: int = 805, drift: float = 0.005, seed: int = 0) -> list[tuple]:
    """(key, true T_world_keyframe, odometry T_world_keyframe, submap points in the keyframe frame) of a simulated
    drive, every 10 m; a host has its own keyframes and clouds instead."""
    sequence = simulate_sequence(seed=seed, frames=frames)
    scans = [sequence.deskewed(index) for index in range(len(sequence))]
    truth = np.array([T for _, T in scans])
    odometry = drifted(truth, drift)
    builder = KeyframeBuilder(SlamConfig().resolved().keyframes)  # street-scale lengths: a city drive
    completed, keyframe_of_frame = [], []
    for i, (scan, _) in enumerate(scans):
        completed.append(builder.add_scan(i, odometry[i], scan.points))
        keyframe_of_frame.append(builder.current_key())
    completed = [keyframe for keyframe in completed + [builder.flush()] if keyframe is not None]
    true_frames = keyframe_frames({kf.key: kf.anchor_frame for kf in completed}, np.array(keyframe_of_frame), truth)
    return [(kf.key, true_frames[kf.key], kf.T_world_keyframe, kf.points) for kf in completed]


def run(data: list[tuple], seed: int = 0) -> HostRun:
    """The host's loop over `keyframes()`: each into ISAM2, the loops from the LoopCloser into ISAM2, the robust
    check at the end."""
    rng = np.random.default_rng(seed)
    isam = gtsam.ISAM2()
    closer = LoopCloser(SlamConfig())
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01] * 3 + [0.1] * 3))  # per 10 m: rad, m
    gps_noise = gtsam.noiseModel.Isotropic.Sigma(3, GPS_SIGMA)
    keys, truth, odometry, loops, loop_slots = [], {}, {}, [], []
    for index, (frame_key, T_true, T_odometry, points) in enumerate(data):
        key = X(frame_key)  # the host's own keys
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if not keys:
            factors.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(T_odometry), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
            values.insert(key, gtsam.Pose3(T_odometry))
        else:
            previous = keys[-1]
            step = gtsam.Pose3(np.linalg.inv(odometry[previous]) @ T_odometry)
            factors.add(gtsam.BetweenFactorPose3(previous, key, step, odometry_noise))
            values.insert(key, isam.calculateEstimate().atPose3(previous).compose(step))
        if index % GPS_EVERY == 0:
            fix = T_true[:3, 3] + rng.normal(scale=GPS_SIGMA, size=3)
            factors.add(gtsam.GPSFactor(key, gtsam.Point3(*fix), gps_noise))
        isam.update(factors, values)
        keys.append(key)
        truth[key], odometry[key] = T_true, T_odometry

        # The loop stage: the host's current estimates in, verified loops out as factors for its own graph.
        estimate = isam.calculateEstimate()
        closer.update_estimates({k: estimate.atPose3(k).matrix() for k in keys})
        found = closer.add_keyframe(key, estimate.atPose3(key).matrix(), points)
        if found:
            new = gtsam.NonlinearFactorGraph()
            for loop in found:
                new.add(loop.between_factor())
            slots = isam.update(new, gtsam.Values()).getNewFactorsIndices()
            loops += found
            loop_slots += list(slots)

    # The robust check on the host's own graph: which of its loop factors to keep (every other factor is trusted).
    kept, _ = check_loops(isam.getFactorsUnsafe(), isam.calculateEstimate(), loop_slots)
    rejected = [slot for slot, keep in zip(loop_slots, kept) if not keep]
    if rejected:
        isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), rejected)
    return HostRun(keys, truth, odometry, isam.calculateEstimate(), loops, kept)


def position_rmse(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float:
    """RMSE [m] of the keyframe positions against the truth (the prior and GPS fix the frame: no alignment)."""
    errors = [np.linalg.norm(poses[key][:3, 3] - truth[key][:3, 3]) for key in truth]
    return float(np.sqrt(np.mean(np.square(errors))))


if __name__ == "__main__":
    host = run(keyframes())
    estimate = {key: host.estimate.atPose3(key).matrix() for key in host.keys}
    print(f"{len(host.keys)} keyframes, {len(host.loops)} loops proposed, {int(host.kept.sum())} kept")
    print(f"keyframe position RMSE: odometry {position_rmse(host.odometry, host.truth):.3f} m, "
          f"with GPS and loops {position_rmse(estimate, host.truth):.3f} m")  # fmt: skip
