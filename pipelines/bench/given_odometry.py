"""The given-odometry part of `sandro-bench slam`: loop closure on top of the odometry of another front end.

The drive's scans deskewed with the true motion (what a LiDAR-inertial front end delivers), and as odometry the true
poses drifting by a share of the distance travelled in a slowly turning direction (`simulation.drift.drifted`).
Per drift: the ATE of the odometry and of sandro-slam on top of it, and the revisit gap of both (`revisit_errors`:
where the drive returns, the error of a pose relative to the earlier pose nearby, median and 95th percentile).
Then sandro-slam on the raw sweeps (with their per-point times) and the same poses, timed at the sweeps' ends,
which deskew the sweeps (`GivenPoses.deskew`): the ATE at the sweeps' starts.
"""

from __future__ import annotations

import numpy as np

from pipelines.evaluation import ate, revisit_errors
from pipelines.simulation import SimulatedSequence
from pipelines.simulation.drift import drifted
from sandro_slam import GivenPoses, OfflineSlam, Scan, SlamConfig


def given_odometry_experiment(
    sequence: SimulatedSequence, frames: list[Scan], config: SlamConfig, drifts: list[float]
) -> dict[str, float]:
    """Metrics `given_<drift %>_*` per drift (a share of the distance, 0.005: 0.5 %)."""
    deskewed = [sequence.deskew(frame) for frame in frames]
    scans = [scan for scan, _ in deskewed]
    truth = np.array([T for _, T in deskewed])
    ends = np.array([scan.timestamp for scan in scans])  # [s] of the sweeps' ends, where `truth` is
    metrics: dict[str, float] = {}
    for drift in drifts:
        name = f"given_{100 * drift:g}pct"
        print(f"sandro-slam on given odometry drifting by {100 * drift:g} % ...", flush=True)
        odometry = drifted(truth, drift)
        result = OfflineSlam(config).run(scans, odometry=GivenPoses(odometry), progress=True)
        metrics[f"{name}_ate_odometry"] = ate(odometry, truth)
        metrics[f"{name}_ate_sandro_slam"] = ate(result.poses, truth)
        metrics[f"{name}_ate_ratio"] = metrics[f"{name}_ate_sandro_slam"] / metrics[f"{name}_ate_odometry"]
        for label, poses in (("odometry", odometry), ("sandro_slam", result.poses)):
            _, errors = revisit_errors(poses, truth)
            if len(errors) == 0:  # a drive that does not return
                continue
            metrics[f"{name}_revisit_gap_median_m_{label}"] = float(np.median(errors[:, 0]))
            metrics[f"{name}_revisit_gap_p95_m_{label}"] = float(np.percentile(errors[:, 0], 95))
            metrics[f"{name}_revisit_gap_median_deg_{label}"] = float(np.median(errors[:, 1]))
        metrics[f"{name}_odometry_noise_scale"] = result.odometry_noise_scale
        metrics[f"{name}_loops_verified"] = len(result.loops)
        metrics[f"{name}_loops_rejected"] = len(result.rejected_loops)
        print("sandro-slam on the raw sweeps, deskewed along that odometry ...", flush=True)
        raw = OfflineSlam(config).run(frames, odometry=GivenPoses(odometry, ends), progress=True)
        metrics[f"{name}_raw_ate_sandro_slam"] = ate(raw.poses, sequence.poses_at(raw.timestamps))
        metrics[f"{name}_raw_loops_rejected"] = len(raw.rejected_loops)
    return metrics
