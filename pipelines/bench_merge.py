"""`sandro-bench merge`: joining simulated sessions that start anywhere (sandro_slam.merge_sessions).

Sessions are sandro-slam runs (OfflineSlam) over simulated drives in one seeded city, each moved by a random
rigid transform (up to 100 m, any yaw) so that no alignment can leak in; computed once per run.
    two:    A drives the default loop around blocks (1,1)-(2,1); B the loop one block east, starting 100 m
            along it: they share two 70 m streets. Session-to-session transform error, B's ATE in the merged
            frame (one SE3 alignment of all merged trajectories) against its single-session ATE, merge time.
    three:  the same plus C on the loop around blocks (1,1)-(1,2), starting 50 m along it.
    refuse: --trials seeds of a wider city (8 blocks east-west); A drives around block (1,1), B around block
            (5,1), 280 m away: the same block template (the city repeats it every two blocks), never seen
            from A. A merge is a failure.
Writes metrics.json, metrics.csv and merge.png into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pipelines.bench_common import UsageError, default_out_dir, pose_errors, write_csv
from pipelines.simulation import CityLayout, simulate_sequence
from pipelines.trajectory_metrics import align_se3, ate
from sandro_slam import OfflineSlam, Session, SlamConfig, merge_sessions

PITCH = CityLayout().pitch
ROUTES = {  # name: (loop, start distance [m])
    "A": (CityLayout().loop, 0.0),
    "B": ((PITCH, 0.0, 3 * PITCH, PITCH), 100.0),
    "C": ((0.0, 0.0, PITCH, 2 * PITCH), 50.0),
}
WIDE = CityLayout(blocks_x=8)
APART = {"A": ((0.0, 0.0, PITCH, PITCH), 0.0), "B": ((4 * PITCH, 0.0, 5 * PITCH, PITCH), 0.0)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `merge` subcommand."""
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_merge/<time>)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: built-in values)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the city, the drives and the frames")
    parser.add_argument("--frames", type=int, default=800, help="frames per session of `two` and `three`")
    parser.add_argument("--trials", type=int, default=20, help="seeded non-overlapping pairs of `refuse`")
    parser.add_argument("--trial-frames", type=int, default=150, help="frames per session of `refuse`")
    parser.add_argument("--skip", default="", help="comma list of parts to skip: two,three,refuse")


class _Sessions:
    """Simulated SLAM sessions, each computed once: (session moved to a random frame, true poses, T_frame_gt)."""

    def __init__(self, config: SlamConfig):
        self.config = config
        self._cache: dict[tuple, tuple[Session, np.ndarray, np.ndarray]] = {}
        self.slam_seconds = 0.0

    def get(self, name: str, seed: int, frames: int, route, layout: CityLayout = CityLayout()):
        key = (name, seed, frames, route, layout)
        if key not in self._cache:
            loop, start = route
            sequence = simulate_sequence(seed=seed, frames=frames, loop=loop, start_distance=start, layout=layout)
            tic = time.perf_counter()
            result = OfflineSlam(self.config).run((f.timestamp, f.points, f.times) for f in sequence.frames())
            self.slam_seconds += time.perf_counter() - tic
            truth = sequence.poses_at(result.timestamps)
            T_frame_world = _random_transform(np.random.default_rng([seed, ord(name[0]), frames]))
            session = Session.from_result(result, name).moved(T_frame_world)
            self._cache[key] = (session, truth, T_frame_world @ np.linalg.inv(truth[0]))
        return self._cache[key]


def _random_transform(rng: np.random.Generator) -> np.ndarray:
    """A rigid transform up to 100 m away with any yaw (and a few degrees of roll/pitch)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [rng.uniform(-np.pi, np.pi), *rng.uniform(-0.05, 0.05, 2)]).as_matrix()
    direction = rng.normal(size=3) * [1, 1, 0.1]
    T[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(0.0, 100.0)
    return T


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; returns the exit code."""
    if args.config is not None and not args.config.is_file():
        raise UsageError(f"no such config file: {args.config}")
    config = SlamConfig.from_yaml(args.config) if args.config else SlamConfig()
    skip = {part.strip() for part in args.skip.split(",") if part.strip()}
    if skip - {"two", "three", "refuse"}:
        raise UsageError(f"unknown parts to skip: {','.join(sorted(skip - {'two', 'three', 'refuse'}))}")
    out = args.out or default_out_dir("bench_merge")
    out.mkdir(parents=True, exist_ok=True)
    cache = _Sessions(config)
    metrics: dict = {"frames_per_session": args.frames, "seed": args.seed}
    plots = {}
    for part, names in (("two", "AB"), ("three", "ABC")):
        if part in skip:
            continue
        print(f"[{part}] sessions {', '.join(names)} ...", flush=True)
        sessions = [cache.get(n, args.seed, args.frames, ROUTES[n]) for n in names]
        result = merge_sessions([s for s, _, _ in sessions], config)
        metrics[part] = _accuracy(sessions, result)
        plots[part] = (sessions, result)
    if "refuse" not in skip:
        metrics["refuse"] = _refusals(cache, args, config)
    metrics["slam_seconds_total"] = cache.slam_seconds
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    write_csv(out / "metrics.csv", _flatten(metrics), ["metric", "value"])
    if plots:
        _plot(out / "merge.png", plots)
    print(json.dumps({k: v for k, v in metrics.items() if k != "refuse"} |
                     {"refuse": {k: v for k, v in metrics.get("refuse", {}).items() if k != "trials"}}, indent=1))
    print(f"results in {out}")
    return 0


def _accuracy(sessions, result) -> dict:
    """Transform errors, ATE single vs in the merged frame, timings of one merge."""
    first, _, T_first = sessions[0]
    out = {"ok": result.ok, "refused": result.refused, "merge_seconds": result.timings.get("total"),
           "timings_s": result.timings, "inter_session_loops_verified": len(result.loops),
           "inter_session_loops_accepted": int(sum(lp.weight >= 0.5 for lp in result.loops))}
    if not result.ok:
        return out
    estimates = np.concatenate([result.frame_poses[s.name] for s, _, _ in sessions])
    truths = np.concatenate([truth for _, truth, _ in sessions])
    aligned = align_se3(estimates, truths) @ estimates
    offset = 0
    for session, truth, T_frame_world in sessions:
        n = len(truth)
        error = aligned[offset:offset + n, :3, 3] - truth[:, :3, 3]
        offset += n
        name = session.name
        out[f"ate_single_{name}"] = ate(session.frame_poses(), truth)
        out[f"ate_merged_{name}"] = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
        out[f"ate_ratio_{name}"] = out[f"ate_merged_{name}"] / out[f"ate_single_{name}"]
        if session is first:
            continue
        T_true = T_first @ np.linalg.inv(T_frame_world)
        rotation, translation = pose_errors(result.T_merged_session[name], T_true)
        out[f"transform_error_m_{name}"] = translation
        out[f"transform_error_deg_{name}"] = rotation
    return out


def _refusals(cache: _Sessions, args: argparse.Namespace, config: SlamConfig) -> dict:
    trials = []
    for trial in range(args.trials):
        seed = args.seed + 1000 + trial
        print(f"[refuse] trial {trial + 1}/{args.trials} (seed {seed}) ...", flush=True)
        a, _, _ = cache.get("A", seed, args.trial_frames, APART["A"], WIDE)
        b, _, _ = cache.get("B", seed, args.trial_frames, APART["B"], WIDE)
        result = merge_sessions([a, b], config)
        agreeing = sum(lp.voted for lp in result.loops)
        trials.append({"seed": seed, "refused": not result.ok, "verified_loops": len(result.loops),
                       "voted_loops": agreeing, "reason": result.refused.get("B", ""),
                       "merge_seconds": result.timings["total"]})
    return {"trials": trials, "refused": sum(t["refused"] for t in trials), "of": len(trials),
            "frames_per_session": args.trial_frames,
            "max_verified_loops": max((t["verified_loops"] for t in trials), default=0),
            "max_voted_loops": max((t["voted_loops"] for t in trials), default=0)}


def _flatten(metrics: dict, prefix: str = "") -> list[dict]:
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows += _flatten(value, f"{prefix}{key}.")
        elif isinstance(value, (int, float, bool)):
            rows.append({"metric": prefix + key, "value": value})
    return rows


def _plot(path: Path, plots: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(plots), figsize=(8 * len(plots), 7), squeeze=False)
    for ax, (part, (sessions, result)) in zip(axes[0], plots.items()):
        for session, _, _ in sessions:
            if session.name in result.frame_poses:
                poses = result.frame_poses[session.name]
                ax.plot(poses[:, 0, 3], poses[:, 1, 3], lw=1.0, label=session.name)
        for loop in result.loops:
            if np.isnan(loop.weight):
                continue
            a = result.keyframe_poses[result.names[loop.target_session]][loop.target_key][:2, 3]
            b = result.keyframe_poses[result.names[loop.source_session]][loop.source_key][:2, 3]
            ax.plot([a[0], b[0]], [a[1], b[1]], "k-" if loop.weight >= 0.5 else "r:", lw=0.7)
        ax.set_aspect("equal")
        ax.set_title(f"{part}: {'merged' if result.ok else 'refused'}")
        ax.legend()
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
