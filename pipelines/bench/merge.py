"""`sandro-bench merge`: joining simulated sessions that start anywhere (sandro_slam.merge_sessions).

Sessions are sandro-slam runs (OfflineSlam) over simulated drives in one seeded city, each moved by a random
rigid transform (up to 100 m, any yaw) so that no alignment can leak in; computed once per run.
    two:    A drives the default loop around blocks (1,1)-(2,1); B the loop one block east, starting 100 m
            along it: they share two 70 m streets.
    three:  the same plus C on the loop around blocks (1,1)-(1,2), starting 50 m along it.
    refuse: --trials seeds (each its own city, template and furniture) of a wider city (8 blocks east-west);
            A drives around block (1,1), B around block (5,1), both from the same point of the block: the same
            block template (the city repeats it every two blocks), so every street B sees looks like one A
            saw, up to the per-block changes and the street furniture. The sessions do not overlap: their
            trajectories stay 210 m apart (x <= 70 m + lane offset against x >= 280 m - lane offset), more than
            twice the sensor range (100 m; submaps keep 30 m), so no place is within range of both. A merge
            is a failure.
With --suite NAMES, `two` and `three` merge sessions of the evaluation suite (`sandro-bench suite --list`)
instead: the first two and the first three named sequences, which must share a site (their world is then the
same), each moved by its own random transform as above; --refine refines each session (OfflineSlam.refine)
before the merge; `refuse` is skipped.
Metrics of `two` and `three`, per session S after the first (A):
    transform_error_{m,deg}_S: T_merged_session[S] against the truth, each session's frame being its first
        pose (the issue's definition). It holds both sessions' own SLAM errors between their first pose and
        the rest of their map (first_pose_error_*, below), which no merge can undo.
    map_transform_error_{m,deg}_S: the same between the sessions' maps: estimate = the rigid fit of S's own
        trajectory onto its merged one; truth = each session's own trajectory fitted rigidly to ground truth.
    overlap_error_{m,deg}_S: median error of S's merged pose relative to the nearest (within 5 m, true
        positions) merged pose of A: how well the maps are registered where they overlap.
    perfect_transform_error_{m,deg}_S, perfect_ate_merged_S, perfect_ate_ratio_S: the same for a reference
        merge that registers perfectly and moves sessions rigidly: each session's own trajectory placed by the
        rigid fit of its frames where they overlap A's onto A's own poses composed with the true relative pose
        (`_perfectly_registered`). What is left there is the sessions' own SLAM errors.
    first_pose_error_{m,deg}_S: the session's first pose against where the rigid fit of its own trajectory
        to ground truth puts it (single-session SLAM, no merge).
    inter_session_loop_error_median_{deg,m}, inter_session_loops_wrong, _wrong_kept, _real_rejected: every
        verified inter-session loop against the true relative pose of its keyframes (wrong: more than 2 deg or
        0.5 m off, as in the suite; the median is of all of them, where the suite's is of the real ones), the
        wrong ones kept in the merged graph, the real ones left out of it.
    variance_factors: each session's and the inter-session loops' (`MergeResult.variance_factors`).
    ate_single_S, ate_merged_S, ate_ratio_S: ATE of S's own run; ATE in the merged frame (one SE3 alignment
        of all merged trajectories together); their ratio. ate_merged_over_perfect_S: ate_merged_S over
        perfect_ate_merged_S (every session, A too). merge_seconds: merge_sessions alone;
        sandro_merge_seconds_from_folders (two): the sandro-merge command on A and B written as results
        folders (out/cli-*/sessions/), reading, merging and writing everything (out/cli-*/merged/).
Writes metrics.json, metrics.csv and merge.png into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pipelines.bench.common import default_out_dir, write_csv
from pipelines.bench.suite import WRONG_LOOP_DEG, WRONG_LOOP_M
from pipelines.evaluation import align_se3, ate, pose_errors
from pipelines.plots import plot_merges
from pipelines.simulation import CityLayout, simulate_sequence
from pipelines.simulation.suite import SUITE, SuiteSequence, cached_frames
from sandro_core.geometry import rigid_fit
from sandro_slam import OfflineSlam, Session, SlamConfig, merge_sessions
from sandro_slam.keyframes import keyframe_frames

PITCH = CityLayout().pitch
ROUTES = {  # name: (loop, start distance [m])
    "A": (CityLayout().loop, 0.0),
    "B": ((PITCH, 0.0, 3 * PITCH, PITCH), 100.0),
    "C": ((0.0, 0.0, PITCH, 2 * PITCH), 50.0),
}
WIDE = CityLayout(blocks_x=8)
APART = {"A": ((0.0, 0.0, PITCH, PITCH), 0.0), "B": ((4 * PITCH, 0.0, 5 * PITCH, PITCH), 0.0)}
OVERLAP_RADIUS = 5.0  # [m] a frame of S overlaps A's nearest frame within this distance (true positions)
SCENE_REACH = 10.0  # [m] how far from a frame the reference merge's perfect registration holds


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `merge` subcommand."""
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_merge/<time>)")
    parser.add_argument("--config", type=Path, help="SlamConfig YAML (default: built-in values)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the city, the drives and the frames")
    parser.add_argument("--frames", type=int, default=800, help="frames per session of `two` and `three`")
    parser.add_argument("--trials", type=int, default=20, help="seeded non-overlapping pairs of `refuse`")
    parser.add_argument("--trial-frames", type=int, default=150, help="frames per session of `refuse`")
    parser.add_argument("--skip", default="", help="comma list of parts to skip: two,three,refuse")
    parser.add_argument(
        "--suite", help="comma list of 2-3 suite sequences of one site: merge those sessions (skips `refuse`)"
    )
    parser.add_argument(
        "--cache", type=Path, default=Path("results/suite_cache"), help="where simulated suite frames are cached"
    )
    parser.add_argument("--refine", action="store_true", help="refine each --suite session before merging")


class _Sessions:
    """Simulated SLAM sessions, each computed once: (session moved to a random frame, true poses, T_given_true: that
    frame from the true world)."""

    def __init__(self, config: SlamConfig):
        self.config = config
        self._cache: dict[tuple, tuple[Session, np.ndarray, np.ndarray]] = {}
        self.slam_seconds = 0.0

    def get(self, name: str, seed: int, frames: int, route, layout: CityLayout = CityLayout()):
        key = (name, seed, frames, route, layout)
        if key not in self._cache:
            loop, start = route
            sequence = simulate_sequence(seed=seed, frames=frames, loop=loop, start_distance=start, layout=layout)
            rng = np.random.default_rng([seed, ord(name[0]), frames])
            self._cache[key] = self._session(name, sequence.frames(), sequence.poses_at, rng)
        return self._cache[key]

    def suite(self, spec: SuiteSequence, seed: int, cache_dir: Path, refine: bool):
        """The session of a suite sequence (all its frames), refined first if `refine`."""
        key = (spec, seed, refine)
        if key not in self._cache:
            frames = cached_frames(spec, cache_dir, progress=True)
            rng = np.random.default_rng([seed, *spec.name.encode()])
            self._cache[key] = self._session(spec.name, frames, spec.truth, rng, refine)
        return self._cache[key]

    def _session(self, name: str, frames, truth_at, rng: np.random.Generator, refine: bool = False):
        """SLAM on `frames` (refined if `refine`: then they must be iterable twice), the session in a random frame."""
        tic = time.perf_counter()
        slam = OfflineSlam(self.config)
        result = slam.run(frames, progress=True)
        if refine:
            result = slam.refine(frames, result, progress=True)
        self.slam_seconds += time.perf_counter() - tic
        truth = truth_at(result.timestamps)
        # The session is handed over in a frame of its own: T_given_slam maps its SLAM world (its first scan) there.
        T_given_slam = _random_transform(rng)
        session = Session.from_result(result, name).moved(T_given_slam)
        return session, truth, T_given_slam @ np.linalg.inv(truth[0])


def _suite_sequences(names: str) -> list[SuiteSequence]:
    """The 2-3 suite sequences of a comma list; all of one site."""
    by_name = {spec.name: spec for spec in SUITE}
    wanted = [name.strip() for name in names.split(",") if name.strip()]
    unknown = [name for name in wanted if name not in by_name]
    if unknown:
        raise ValueError(f"unknown suite sequences: {', '.join(unknown)} (sandro-bench suite --list)")
    if not 2 <= len(wanted) <= 3 or len(set(wanted)) != len(wanted):
        raise ValueError(f"--suite takes 2 or 3 different sequences, got {len(wanted)}: {names}")
    sites = {by_name[name].site for name in wanted}
    if len(sites) > 1:
        raise ValueError(f"--suite sequences must share a site, got {', '.join(sorted(sites))}")
    return [by_name[name] for name in wanted]


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
    config = SlamConfig.load(args.config)
    skip = {part.strip() for part in args.skip.split(",") if part.strip()}
    if skip - {"two", "three", "refuse"}:
        raise ValueError(f"unknown parts to skip: {','.join(sorted(skip - {'two', 'three', 'refuse'}))}")
    specs = _suite_sequences(args.suite) if args.suite else []
    out = args.out or default_out_dir("bench_merge")
    out.mkdir(parents=True, exist_ok=True)
    cache = _Sessions(config)
    metrics: dict = {"seed": args.seed}
    if specs:
        skip |= {"refuse"} | ({"three"} if len(specs) < 3 else set())
        metrics |= {"suite": [spec.name for spec in specs], "refine": args.refine}
        get = {spec.name: lambda spec=spec: cache.suite(spec, args.seed, args.cache, args.refine) for spec in specs}
    else:
        metrics["frames_per_session"] = args.frames
        get = {name: lambda name=name: cache.get(name, args.seed, args.frames, ROUTES[name]) for name in "ABC"}
    plots = {}
    for part, count in (("two", 2), ("three", 3)):
        if part in skip:
            continue
        names = list(get)[:count]
        print(f"[{part}] sessions {', '.join(names)} ...", flush=True)
        sessions = [get[name]() for name in names]
        result = merge_sessions([s for s, _, _ in sessions], config)
        metrics[part] = _accuracy(sessions, result)
        plots[f"{part}: {'merged' if result.ok else 'refused'}"] = result
        if part == "two":
            metrics[part]["sandro_merge_seconds_from_folders"] = _time_cli(out, [s for s, _, _ in sessions])
    if "refuse" not in skip:
        metrics["refuse"] = _refusals(cache, args, config)
    metrics["slam_seconds_total"] = cache.slam_seconds
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    write_csv(out / "metrics.csv", _flatten(metrics), ["metric", "value"])
    if plots:
        plot_merges(out / "merge.png", plots)
    print(
        json.dumps(
            {k: v for k, v in metrics.items() if k != "refuse"}
            | {"refuse": {k: v for k, v in metrics.get("refuse", {}).items() if k != "trials"}},
            indent=1,
        )
    )
    print(f"results in {out}")
    return 0


def _accuracy(sessions, result) -> dict:
    """Transform errors, ATE single vs in the merged frame, timings of one merge."""
    first, _, T_first = sessions[0]
    out = {
        "ok": result.ok,
        "refused": result.refused,
        "merge_seconds": result.timings.get("total"),
        "variance_factors": result.variance_factors,
        "timings_s": result.timings,
        "inter_session_loops_verified": len(result.loops),
        "inter_session_loops_accepted": int(sum(lp.weight >= 0.5 for lp in result.loops)),
    }
    if not result.ok:
        return out
    truths = [truth for _, truth, _ in sessions]
    own = [session.frame_poses() for session, _, _ in sessions]  # each session's single-session poses
    fits = [align_se3(poses, truth) for poses, truth in zip(own, truths)]  # each onto its truth
    placed = [np.eye(4)] + [
        _perfectly_registered(own[0], truths[0], poses, truth) for poses, truth in zip(own[1:], truths[1:])
    ]
    merged_ate = _joint_ate([result.frame_poses[s.name] for s, _, _ in sessions], truths)
    perfect_ate = _joint_ate([T @ poses for T, poses in zip(placed, own)], truths)
    for index, (session, truth, T_given_true) in enumerate(sessions):
        name = session.name
        out[f"ate_single_{name}"] = ate(own[index], truth)
        out[f"ate_merged_{name}"] = merged_ate[index]
        out[f"ate_ratio_{name}"] = merged_ate[index] / out[f"ate_single_{name}"]
        out[f"perfect_ate_merged_{name}"] = perfect_ate[index]
        out[f"perfect_ate_ratio_{name}"] = perfect_ate[index] / out[f"ate_single_{name}"]
        out[f"ate_merged_over_perfect_{name}"] = merged_ate[index] / perfect_ate[index]
        _put(out, "first_pose_error", name, pose_errors(fits[index], np.linalg.inv(T_given_true)))
        if index == 0:
            continue
        T_true = T_first @ np.linalg.inv(T_given_true)
        _put(out, "transform_error", name, pose_errors(result.T_merged_session[name], T_true))
        _put(out, "perfect_transform_error", name, pose_errors(placed[index], T_true))
        _put(
            out,
            "map_transform_error",
            name,
            pose_errors(align_se3(own[index], result.frame_poses[name]), np.linalg.inv(fits[0]) @ fits[index]),
        )
        _put(
            out,
            "overlap_error",
            name,
            _overlap_error(result.frame_poses[first.name], truths[0], result.frame_poses[name], truth),
        )
    tested = [lp.conflict for lp in result.loops if not np.isnan(lp.conflict)]
    out["free_space_conflict_median"] = float(np.median(tested)) if tested else None
    out.update(_loops_against_truth(sessions, result))
    return out


def _loops_against_truth(sessions, result) -> dict[str, float | int]:
    """The inter-session loops against the true relative pose of their keyframe frames: median error,
    wrong ones (more than WRONG_LOOP_DEG or WRONG_LOOP_M off) kept in the merged graph, real ones rejected (by the
    vote or the back end)."""
    frames = [
        keyframe_frames(_anchor_frames(session), session.keyframe_of_frame, truth) for session, truth, _ in sessions
    ]
    errors, kept = [], []
    for loop in result.loops:
        target = frames[loop.target_session][loop.target_key]
        source = frames[loop.source_session][loop.source_key]
        errors.append(pose_errors(loop.T_target_source, np.linalg.inv(target) @ source))
        kept.append(loop.weight >= 0.5)
    if not errors:
        return {}
    errors, kept = np.array(errors), np.array(kept)
    wrong = (errors[:, 0] > WRONG_LOOP_DEG) | (errors[:, 1] > WRONG_LOOP_M)
    return {
        "inter_session_loop_error_median_deg": float(np.median(errors[:, 0])),
        "inter_session_loop_error_median_m": float(np.median(errors[:, 1])),
        "inter_session_loops_wrong": int(wrong.sum()),
        "inter_session_loops_wrong_kept": int((wrong & kept).sum()),
        "inter_session_loops_real_rejected": int((~wrong & ~kept).sum()),
    }


def _anchor_frames(session: Session) -> dict[int, int]:
    """Per keyframe key, its anchor scan: the frame at the keyframe frame's position."""
    offsets = np.linalg.norm(session.T_keyframe_frame[:, :3, 3], axis=1)
    anchors = {}
    for key in session.keys:
        mine = np.flatnonzero(session.keyframe_of_frame == key)
        anchors[int(key)] = int(mine[np.argmin(offsets[mine])])
    return anchors


def _put(out: dict, metric: str, name: str, errors: tuple[float, float]) -> None:
    out[f"{metric}_m_{name}"], out[f"{metric}_deg_{name}"] = errors[1], errors[0]


def _joint_ate(estimates: list[np.ndarray], truths: list[np.ndarray]) -> list[float]:
    """ATE [m] of each (F, 4, 4) trajectory after one SE3 alignment of all of them together onto the truth."""
    stacked, truth = np.concatenate(estimates), np.concatenate(truths)
    errors = np.split(
        (align_se3(stacked, truth) @ stacked)[:, :3, 3] - truth[:, :3, 3], np.cumsum([len(t) for t in truths])[:-1]
    )
    return [float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) for e in errors]


def _overlapping(truth_a: np.ndarray, truth_s: np.ndarray, radius: float = OVERLAP_RADIUS):
    """(frames of S within `radius` [m] of a frame of A, that frame of A for each), by true position."""
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(truth_a[:, :3, 3]).query(truth_s[:, :3, 3])
    close = np.flatnonzero(distance < radius)
    return close, nearest[close]


def _perfectly_registered(
    poses_a: np.ndarray, truth_a: np.ndarray, poses_s: np.ndarray, truth_s: np.ndarray
) -> np.ndarray:
    """T (4x4, A's frame <- S's) of a rigid merge whose registration is perfect: where S's frames overlap A's,
    each of S's frames belongs where A's nearest frame (A's own pose) and the true relative pose put it; T is
    the rigid fit of what S's frames hold there, their origins and a point `SCENE_REACH` metres along each
    of their axes, onto the same points of the frames where they belong (as registering the scans around
    them would align them, which positions alone cannot do along a single straight street)."""
    close, nearest = _overlapping(truth_a, truth_s)
    if len(close) < 3:
        raise ValueError(f"only {len(close)} frames of the session lie within {OVERLAP_RADIUS} m of the first's")
    wanted = poses_a[nearest] @ np.linalg.inv(truth_a[nearest]) @ truth_s[close]
    return rigid_fit(_scene_points(poses_s[close]), _scene_points(wanted))


def _scene_points(poses: np.ndarray) -> np.ndarray:
    """(4N, 3): each of the (N, 4, 4) poses' origin and the points `SCENE_REACH` along its x, y and z axes."""
    offsets = np.vstack([np.zeros(3), SCENE_REACH * np.eye(3)])
    return (np.einsum("nij,kj->nki", poses[:, :3, :3], offsets) + poses[:, None, :3, 3]).reshape(-1, 3)


def _overlap_error(
    merged_a: np.ndarray, truth_a: np.ndarray, merged_s: np.ndarray, truth_s: np.ndarray
) -> tuple[float, float]:
    """Median (rotation [deg], translation [m]) error of S's poses relative to A's nearest pose within
    `OVERLAP_RADIUS` (true positions): the registration error where the sessions overlap; nan without overlap."""
    close, nearest = _overlapping(truth_a, truth_s)
    if len(close) == 0:
        return float("nan"), float("nan")
    errors = [
        pose_errors(np.linalg.inv(merged_a[a]) @ merged_s[f], np.linalg.inv(truth_a[a]) @ truth_s[f])
        for f, a in zip(close, nearest)
    ]
    return tuple(float(v) for v in np.median(errors, axis=0))


def _time_cli(out: Path, sessions: list[Session]) -> float:
    """Seconds `sandro-merge` takes on the sessions written as results folders (reading, merging, writing
    every output into out/cli-*/merged)."""
    import tempfile

    from pipelines.cli.merge import main
    from pipelines.io.session import save_session

    folder = Path(tempfile.mkdtemp(prefix="cli-", dir=out))
    for session in sessions:
        (folder / "sessions" / session.name).mkdir(parents=True)
        save_session(folder / "sessions" / session.name, session)
    tic = time.perf_counter()
    code = main([str(folder / "sessions" / s.name) for s in sessions] + ["--out", str(folder / "merged")])
    seconds = time.perf_counter() - tic
    if code != 0:
        raise RuntimeError(f"sandro-merge on the written sessions exited with {code}")
    return seconds


def _refusals(cache: _Sessions, args: argparse.Namespace, config: SlamConfig) -> dict:
    trials = []
    for trial in range(args.trials):
        seed = args.seed + 1000 + trial
        print(f"[refuse] trial {trial + 1}/{args.trials} (seed {seed}) ...", flush=True)
        a, _, _ = cache.get("A", seed, args.trial_frames, APART["A"], WIDE)
        b, _, _ = cache.get("B", seed, args.trial_frames, APART["B"], WIDE)
        result = merge_sessions([a, b], config)
        tested = [lp.conflict for lp in result.loops if not np.isnan(lp.conflict)]
        trials.append(
            {
                "seed": seed,
                "refused": not result.ok,
                "verified_loops": len(result.loops),
                "agreeing_loops_tested": len(tested),
                "free_space_conflict_median": float(np.median(tested)) if tested else None,
                "reason": result.refused.get("B", ""),
                "merge_seconds": result.timings["total"],
            }
        )
    medians = [t["free_space_conflict_median"] for t in trials if t["free_space_conflict_median"] is not None]
    return {
        "trials": trials,
        "refused": sum(t["refused"] for t in trials),
        "of": len(trials),
        "frames_per_session": args.trial_frames,
        "max_verified_loops": max((t["verified_loops"] for t in trials), default=0),
        "trials_reaching_the_free_space_test": len(medians),
        "min_free_space_conflict_median": min(medians, default=None),
        "max_free_space_conflict_median": max(medians, default=None),
    }


def _flatten(metrics: dict, prefix: str = "") -> list[dict]:
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows += _flatten(value, f"{prefix}{key}.")
        elif isinstance(value, (int, float, bool)):
            rows.append({"metric": prefix + key, "value": value})
    return rows
