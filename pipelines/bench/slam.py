"""`sandro-bench slam`: the SLAM pipeline on a simulated drive, beside KISS-ICP alone and KISS-SLAM.

The drive (`pipelines.simulation.simulate_sequence`): a 32-beam spinning LiDAR, two laps through a city of
repeated and mirror-symmetric blocks, ~800 sweeps at 1 m spacing, raw (not deskewed) points with
per-point times. Measured:
    accuracy: ATE (RMSE after an SE3 alignment) of KISS-ICP alone, of sandro-slam and of KISS-SLAM, of the last
        run and of every run (`*_runs`: KISS-ICP's poses differ in their last digits from run to run);
    ate_keyframe_floor: the ATE a perfect loop closure of this design could reach: every keyframe's scans
        moved rigidly onto the truth (a best fit per keyframe), leaving only KISS-ICP's errors inside a keyframe;
    speed: frames/s of each pipeline and of KISS-ICP alone, and the share loop closure adds to the odometry
        time: sandro-slam's time beyond KISS-ICP alone's, over KISS-ICP alone's (with `loops.in_background`
        that is the work left in the main process, the odometry's slowdown from the worker and the wait for
        it at the end; the worker's CPU time is reported apart). The frames are simulated (float64, as the
        simulator makes them: ~0.7 GB for the default drive) before any pipeline runs, so that the times cover
        the pipeline alone, from its first frame to its final poses, and not the raycasting that makes the
        frames. sandro-slam, KISS-SLAM and KISS-ICP alone run in turn --repeats times and the median rate
        counts (a single run of either varies by up to 15 %);
    loops against the truth: each verified loop's error against the true relative pose of its keyframes;
        loops_wrong: those off by more than WRONG_LOOP_M or WRONG_LOOP_DEG (the front end's false positives,
        e.g. a street that looks like another); how many of them and of the real ones the back end rejected;
    false loops: wrong loop factors (30 % more than the true ones: random keyframe pairs with plausible
        small transforms) added to sandro-slam's final graph, optimised by its robust back end and by plain
        least squares (what KISS-SLAM does): ATE and how many were rejected;
    given odometry: sandro-slam on the deskewed scans and the odometry of a simulated LiDAR-inertial front end,
        drifting by each of --given-drifts (`bench.given_odometry`): ATE and revisit gap, before and after;
    damaged input: the drive with sweeps lost and sweeps cut short (`bench.damaged_input`): frames skipped, ATE.
Writes metrics.json, metrics.csv and trajectories.png into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import gtsam
import numpy as np
from kiss_icp.kiss_icp import KissICP

from pipelines.bench.bags import bag_experiment
from pipelines.bench.common import default_out_dir, write_csv
from pipelines.bench.damaged_input import damaged_input_experiment
from pipelines.bench.given_odometry import given_odometry_experiment
from pipelines.bench.kiss_slam import kiss_slam_available, run_kiss_slam
from pipelines.evaluation import align_se3, ate, pose_errors, sweep_end_stamps
from pipelines.io.trajectory import write_tum
from pipelines.plots import plot_trajectories
from pipelines.simulation import simulate_sequence
from sandro_slam import OfflineSlam, SlamConfig, SlamResult
from sandro_slam.config import GraphConfig
from sandro_slam.factors import between_factor
from sandro_slam.keyframes import keyframe_frames
from sandro_slam.robust_backend import robust_optimize

WRONG_LOOP_M = 1.0  # a verified loop this far off the truth is a false positive of the front end
WRONG_LOOP_DEG = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `slam` subcommand."""
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_slam/<time>)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: configs/default.yaml's values)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated city and drive")
    parser.add_argument("--laps", type=int, default=2, help="laps of the drive")
    parser.add_argument("--frames", type=int, help="at most this many frames")
    parser.add_argument(
        "--false-loop-ratio", type=float, default=0.3, help="wrong loops added, as a share of the true ones"
    )
    parser.add_argument("--no-kiss-slam", action="store_true", help="skip the KISS-SLAM baseline")
    parser.add_argument(
        "--repeats", type=int, default=3, help="runs of sandro-slam and KISS-SLAM, in turn; frames/s is their median"
    )
    parser.add_argument(
        "--given-drifts",
        default="0.5,0.05",
        help="drifts [%% of the distance] of the given odometry runs, comma list ('' for none; default 0.5,0.05)",
    )
    parser.add_argument(
        "--no-damaged-input", action="store_true", help="skip the run with sweeps lost and sweeps cut short"
    )
    parser.add_argument(
        "--no-bags",
        action="store_true",
        help="skip the runs from bags (each format, end to end) and the bag reading speed",
    )


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; returns the exit code."""
    if args.repeats < 1:
        raise ValueError(f"--repeats {args.repeats}: expected at least 1")
    config = SlamConfig.load(args.config)
    out = args.out or default_out_dir("bench_slam")
    out.mkdir(parents=True, exist_ok=True)
    sequence = simulate_sequence(seed=args.seed, laps=args.laps, frames=args.frames)
    frames = list(sequence.frames())
    end_stamps = sweep_end_stamps(frames)  # KISS-SLAM's poses refer to the sweeps' ends, sandro-slam's to their middles

    kiss_slam = not args.no_kiss_slam and kiss_slam_available()
    fps: dict[str, list[float]] = {"sandro_slam": [], "kiss_slam": [], "kiss_icp": []}
    ates: dict[str, list[float]] = {"kiss_icp": [], "sandro_slam": [], "kiss_slam": []}  # KISS-ICP's poses are
    # not bit-identical from run to run, and what follows from them can tip: every run's ATE is reported
    for repeat in range(args.repeats):
        result = OfflineSlam(config).run(frames, progress=True)
        n = len(result.timestamps)
        truth = sequence.poses_at(result.timestamps)
        fps["sandro_slam"].append(n / result.timings["total"])
        ates["kiss_icp"].append(ate(result.odometry_poses, truth))
        ates["sandro_slam"].append(ate(result.poses, truth))
        if kiss_slam:
            print(f"KISS-SLAM on the same frames (run {repeat + 1}) ...", flush=True)
            kiss_poses, seconds = run_kiss_slam(frames, config.odometry.data.max_range)
            fps["kiss_slam"].append(n / seconds)
            ates["kiss_slam"].append(ate(kiss_poses, sequence.poses_at(end_stamps)))
        print(f"KISS-ICP alone on the same frames (run {repeat + 1}) ...", flush=True)
        fps["kiss_icp"].append(n / kiss_icp_seconds(frames, result.config))
    metrics = {
        "frames": n,
        "keyframes": len(result.keyframes),
        "loops_verified": len(result.loops),
        "loops_rejected_by_back_end": len(result.rejected_loops),
        "ate_kiss_icp": ates["kiss_icp"][-1],
        "ate_kiss_icp_runs": ates["kiss_icp"],
        "ate_sandro_slam": ates["sandro_slam"][-1],
        "ate_sandro_slam_runs": ates["sandro_slam"],
        "ate_keyframe_floor": keyframe_floor(result, truth),
        "fps_kiss_icp": float(np.median(fps["kiss_icp"])),
        "fps_kiss_icp_runs": fps["kiss_icp"],
        "fps_sandro_slam": float(np.median(fps["sandro_slam"])),
        "fps_sandro_slam_runs": fps["sandro_slam"],
        "loop_closure_share_of_odometry": float(np.median(fps["kiss_icp"]) / np.median(fps["sandro_slam"]) - 1.0),
        "timings_s": result.timings,
        "loops_found_by": dict(Counter(loop.found_by for loop in result.loops)),
        **loops_against_truth(result, truth),
    }
    trajectories = {"KISS-ICP": result.odometry_poses, "sandro-slam": result.poses}
    if kiss_slam:
        metrics["ate_kiss_slam"] = ates["kiss_slam"][-1]
        metrics["ate_kiss_slam_runs"] = ates["kiss_slam"]
        metrics["fps_kiss_slam"] = float(np.median(fps["kiss_slam"]))
        metrics["fps_kiss_slam_runs"] = fps["kiss_slam"]
        trajectories["KISS-SLAM"] = kiss_poses
    metrics.update(false_loop_experiment(result, truth, config.graph, args.false_loop_ratio, args.seed))
    drifts = [float(value) / 100.0 for value in args.given_drifts.split(",") if value.strip()]
    if drifts:
        metrics.update(given_odometry_experiment(sequence, frames, config, drifts))
    if not args.no_damaged_input:
        metrics.update(damaged_input_experiment(sequence, frames, config))
    if not args.no_bags:
        del frames  # the bag runs stream their frames
        metrics.update(bag_experiment(out, config, args.seed, args.laps, args.frames))

    for name, poses in {"ground truth": truth, **trajectories}.items():
        stamps = end_stamps if name == "KISS-SLAM" else result.timestamps
        write_tum(out / f"{name.replace(' ', '_')}.tum", stamps, poses)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    write_csv(
        out / "metrics.csv",
        [{"metric": k, "value": v} for k, v in metrics.items() if np.isscalar(v)],
        ["metric", "value"],
    )
    plot_trajectories(
        out / "trajectories.png",
        result.timestamps,
        truth,
        trajectories,
        f"{len(result.timestamps)} frames, {len(result.loops)} verified loops",
    )
    _print(metrics)
    print(f"results in {out}")
    return 0


def kiss_icp_seconds(frames: list, config: SlamConfig) -> float:
    """Wall time [s] of KISS-ICP alone, configured as sandro-slam's odometry, over the frames."""
    odometry = KissICP(config.odometry)
    start = time.perf_counter()
    for _, points, times in frames:
        odometry.register_frame(points, times)
    return time.perf_counter() - start


def keyframe_floor(result: SlamResult, truth: np.ndarray) -> float:
    """RMSE [m] of the odometry positions after a rigid fit of each keyframe's scans to the truth (`truth`:
    (F, 4, 4) at the result's frames). sandro-slam moves every scan with its keyframe, so no loop closure can
    bring its ATE below this: it is KISS-ICP's error within the span of a keyframe."""
    squared = []
    for keyframe in result.keyframes:
        mine = result.keyframe_of_frame == keyframe.key
        fitted = align_se3(result.odometry_poses[mine], truth[mine]) @ result.odometry_poses[mine]
        squared.append(np.sum((fitted[:, :3, 3] - truth[mine][:, :3, 3]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(squared))))


def loops_against_truth(
    result: SlamResult, truth: np.ndarray, wrong_m: float = WRONG_LOOP_M, wrong_deg: float = WRONG_LOOP_DEG
) -> dict[str, float]:
    """The verified loops against the true relative poses of their keyframe frames (`truth`: (F, 4, 4) at the
    result's frames): median errors, the wrong ones (beyond `wrong_m` [m] or `wrong_deg` [deg]) and how many of
    them, and of the real ones, the back end rejected; and how many of the wrong ones kept are wrong against
    their submaps' own frames too (`submap_frames`): the others are right about the submaps, and what is off is
    where the odometry placed the keyframe's scans within it."""
    if not result.loops:
        return {"loops_wrong": 0}
    errors = loop_errors(result, truth)
    wrong = (errors[:, 1] > wrong_m) | (errors[:, 0] > wrong_deg)
    rejected = np.array([loop.weight < 0.5 for loop in result.loops])
    median_deg, median_m = np.median(errors[~wrong], axis=0) if (~wrong).any() else (np.nan, np.nan)
    metrics = {
        "loop_error_median_deg": float(median_deg),
        "loop_error_median_m": float(median_m),
        "loops_wrong": int(wrong.sum()),
        "loops_wrong_rejected": int((wrong & rejected).sum()),
        "loops_real_rejected": int((~wrong & rejected).sum()),
    }
    submap_errors = loop_errors(result, truth, submap_frames(result, truth))
    submap_wrong = (submap_errors[:, 1] > wrong_m) | (submap_errors[:, 0] > wrong_deg)
    metrics["loops_wrong_kept_submap_frames"] = int((wrong & submap_wrong & ~rejected).sum())
    return metrics


def result_keyframe_truths(result: SlamResult, truth: np.ndarray) -> dict[int, np.ndarray]:
    """Per key, the true pose of a SLAM result's keyframe frame (`keyframes.keyframe_frames` of the true poses,
    `truth` (F, 4, 4) at the result's frames)."""
    anchors = {keyframe.key: keyframe.anchor_frame for keyframe in result.keyframes}
    return keyframe_frames(anchors, result.keyframe_of_frame, truth)


def loop_errors(result: SlamResult, truth: np.ndarray, corrections: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """(L, 2) [deg, m]: each verified loop's error against the true relative pose of its keyframe frames (`truth`:
    (F, 4, 4) at the result's frames), or, with `corrections` (`submap_frames`), of their submaps' frames."""
    true_pose = result_keyframe_truths(result, truth)
    errors = []
    for loop in result.loops:
        T_true = np.linalg.inv(true_pose[loop.target_key]) @ true_pose[loop.source_key]
        if corrections is not None:
            T_true = np.linalg.inv(corrections[loop.target_key]) @ T_true @ corrections[loop.source_key]
        errors.append(pose_errors(loop.T_target_source, T_true))
    return np.array(errors).reshape(-1, 2)


def submap_frames(result: SlamResult, truth: np.ndarray) -> dict[int, np.ndarray]:
    """Per keyframe, the rigid transform E (4x4) from the frame its submap is built in (the odometry's) to the true
    keyframe frame that best fits its scans: E @ T_keyframe_frame ~ the scans' true poses relative to the
    keyframe frame's truth (`result_keyframe_truths`; rotation: the chordal mean; translation: the mean offset).
    Identity where the odometry within the keyframe is right; a keyframe whose scans bend has its submap turned by E
    against its frame's truth, and a loop that aligns the submaps right is that far off the frames' truth."""
    true_pose = result_keyframe_truths(result, truth)
    corrections = {}
    for keyframe in result.keyframes:
        mine = np.flatnonzero(result.keyframe_of_frame == keyframe.key)
        true_relative = np.linalg.inv(true_pose[keyframe.key]) @ truth[mine]
        odometry_relative = result.T_keyframe_frame[mine]
        u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", true_relative[:, :3, :3], odometry_relative[:, :3, :3]))
        E = np.eye(4)
        E[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        E[:3, 3] = np.mean(true_relative[:, :3, 3] - odometry_relative[:, :3, 3] @ E[:3, :3].T, axis=0)
        corrections[keyframe.key] = E
    return corrections


def false_loop_experiment(
    result: SlamResult, truth: np.ndarray, graph_config: GraphConfig, ratio: float, seed: int
) -> dict[str, float]:
    """Add wrong loops to the final keyframe graph; ATE and rejection with the robust back end and with plain
    least squares."""
    accepted = [loop for loop in result.loops if loop.weight >= 0.5]
    keys = [keyframe.key for keyframe in result.keyframes]
    if not accepted or len(keys) < 4:
        return {}
    rng = np.random.default_rng(seed)
    graph = gtsam.NonlinearFactorGraph(result.graph)
    covariance = np.median(np.stack([loop.covariance for loop in accepted]), axis=0)
    first_false = graph.size()
    n_false = max(1, int(round(ratio * len(accepted))))
    for _ in range(n_false):
        a, b = rng.choice(keys, size=2, replace=False)
        wrong = gtsam.Pose3(gtsam.Rot3.Yaw(rng.uniform(-0.5, 0.5)), gtsam.Point3(*rng.uniform(-5.0, 5.0, 3)))
        graph.add(between_factor(int(a), int(b), wrong.matrix(), covariance))
    known = [i for i in range(first_false) if not _is_loop(i, result)]
    out = {"false_loops_added": n_false}
    for name, robust in (("robust", graph_config.robust), ("least_squares", "none")):
        config = graph_config.model_copy(update={"robust": robust})
        values, weights = robust_optimize(graph, result.values, known, config)
        poses = result.frame_poses({k: values.atPose3(k).matrix() for k in keys})
        out[f"ate_with_false_loops_{name}"] = ate(poses, truth)
        out[f"false_loops_rejected_{name}"] = float(np.mean(weights[first_false:] < 0.5))
    out["ate_clean"] = ate(result.poses, truth)
    return out


def _is_loop(factor_index: int, result: SlamResult) -> bool:
    return any(loop.factor.factor_index == factor_index for loop in result.loops)


def _print(metrics: dict) -> None:
    print()
    for key, value in metrics.items():
        if isinstance(value, float):
            print(f"{key:40s} {value:10.3f}")
        else:
            print(f"{key:40s} {value}")
