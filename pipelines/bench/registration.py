"""`sandro-bench registration`: every solver on the same correspondences, in one run.

Parts:
    synthetic: outlier-rate sweep (0-99 %, uniform and structured outliers, N = 1000) from
        `pipelines.synthetic.make_problem`.
    real: the small_gicp pair and KITTI 07 keyframe pairs; per trial the source cloud is moved by a
        random rigid transform (any rotation, up to 10 m), matched to the target with FPFH
        (`sandro_core.features.match_fpfh`), and every solver runs on those matches.
    scale: time and peak memory against the number of correspondences (`pipelines.bench_scale`).
A trial succeeds at rotation error <= 10 deg and translation error <= 1 m (strict: 5 deg and 0.6 m).
Writes into --out: trials.csv (one row per solver and trial; `case` is the outlier rate or the pair),
summary.csv, scale.csv, registration.png and settings.json (the resolved options).
"""

from __future__ import annotations

import argparse
import json
import time
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipelines.bench.baselines import Solver
from pipelines.bench.common import default_out_dir, parse_int_list, parse_list, write_csv
from pipelines.bench.registration_report import SUMMARY_FIELDS, format_tables, plot_results, summarize
from pipelines.bench.scale import SCALE_FIELDS, SCALE_SIZES, scale_rows
from pipelines.bench.solvers import SOLVERS, warm_up
from pipelines.evaluation import pose_errors
from pipelines.io.pointclouds import load_point_cloud
from pipelines.io.trajectory import read_keyframe_poses, read_transform
from pipelines.simulation.correspondences import make_problem, random_transform
from sandro_core.features import match_fpfh
from sandro_core.geometry import transform_points

PARTS = ("synthetic", "real", "scale")
OUTLIER_RATES = (0.0, 0.5, 0.8, 0.9, 0.95, 0.98, 0.99)
OUTLIER_KINDS = ("uniform", "structured")
SYNTHETIC_N = 1000
KITTI_PAIRS = ((0, 1), (0, 2), (1, 3), (2, 4), (0, 3))  # (target, source) keyframe indices
MOVE_MAX_TRANSLATION = 10.0  # [m], of the random transform applied to real source clouds
SUCCESS_THRESHOLDS = {"success_10deg_1m": (10.0, 1.0), "success_5deg_0.6m": (5.0, 0.6)}  # [deg], [m]
TRIAL_FIELDS = [
    "part", "solver", "case", "outlier_kind", "trial", "n_corr", "inlier_ratio",
    "rot_err_deg", "trans_err_m", "time_s", *SUCCESS_THRESHOLDS, "error",
]  # fmt: skip


@dataclass(frozen=True)
class Case:
    """One set of putative correspondences that every solver gets."""

    part: str
    case: str  # outlier rate (synthetic) or pair name (real)
    outlier_kind: str  # uniform / structured (synthetic), fpfh (real)
    trial: int
    source: np.ndarray  # (N, 3) [m], source frame
    target: np.ndarray  # (N, 3) [m], target frame
    T_target_source: np.ndarray  # ground truth
    noise_bound: float  # [m]


@dataclass(frozen=True)
class Pair:
    """Two real scans and the ground truth that maps source points into the target frame."""

    name: str
    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `registration` subcommand."""
    parser.add_argument("--data", type=Path, help="folder with small_gicp/ and/or kitti07/ (for part 'real')")
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_registration/<time>)")
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma list of {','.join(PARTS)} (default all)")
    parser.add_argument("--solvers", default=",".join(SOLVERS), help=f"comma list of {','.join(SOLVERS)}")
    parser.add_argument("--trials", type=int, help="trials per outlier rate and kind (default 40; 2 with --quick)")
    parser.add_argument("--pair-trials", type=int, help="trials per real pair (default 10; 1 with --quick)")
    parser.add_argument("--voxel-size", type=float, default=0.5, help="FPFH voxel for real pairs [m] (0.5)")
    parser.add_argument("--noise-bound", type=float, help="solver noise bound on real pairs [m] (the voxel size)")
    parser.add_argument(
        "--scale-sizes",
        help=f"comma list of N for part 'scale' (default {','.join(map(str, SCALE_SIZES))}; 1000 with --quick)",
    )
    parser.add_argument("--time-limit", type=float, default=60.0, help="skip scale runs predicted above this [s]")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice (0)")
    parser.add_argument("--quick", action="store_true", help="few trials and sizes: a smoke test")


def load_pairs(data_dir: Path) -> list[Pair]:
    """The real pairs under `data_dir`: small_gicp/{source,target}.ply + T_target_source.txt, and
    kitti07/00000N.bin + poses.txt (`vN x y z qx qy qz qw`), whose pair (a, b) maps b into a.

    Raises:
        ValueError: a missing folder or file, or an unreadable one.
    """
    if not data_dir.is_dir():
        raise ValueError(f"--data {data_dir}: no such folder")
    small, kitti = data_dir / "small_gicp", data_dir / "kitti07"
    if not small.is_dir() and not kitti.is_dir():
        raise ValueError(f"--data {data_dir}: holds neither small_gicp/ nor kitti07/")
    pairs = []
    try:
        if small.is_dir():
            source, target = load_point_cloud(small / "source.ply"), load_point_cloud(small / "target.ply")
            pairs.append(Pair("small_gicp", source, target, read_transform(small / "T_target_source.txt")))
        if kitti.is_dir():
            poses = read_keyframe_poses(kitti / "poses.txt")
            for a, b in KITTI_PAIRS:
                if a not in poses or b not in poses:
                    raise ValueError(f"{kitti / 'poses.txt'}: no pose for keyframe {a if a not in poses else b}")
                source, target = load_point_cloud(kitti / f"{b:06d}.bin"), load_point_cloud(kitti / f"{a:06d}.bin")
                pairs.append(Pair(f"kitti07_{a}_{b}", source, target, np.linalg.inv(poses[a]) @ poses[b]))
    except (OSError, ValueError) as error:
        raise ValueError(str(error)) from None
    return pairs


def synthetic_cases(trials: int, seed: int) -> Iterator[Case]:
    """N = 1000 problems per outlier kind, rate and trial; each seeded by (seed, kind, rate, trial)."""
    for kind_index, kind in enumerate(OUTLIER_KINDS):
        for rate in OUTLIER_RATES:
            for trial in range(trials):
                rng = np.random.default_rng([seed, 0, kind_index, round(rate * 100), trial])
                problem = make_problem(rng, SYNTHETIC_N, rate, kind)
                yield Case(
                    "synthetic", f"{rate:.2f}", kind, trial,
                    problem.source, problem.target, problem.T_target_source, problem.noise_bound,
                )  # fmt: skip


def real_cases(pairs: list[Pair], trials: int, seed: int, voxel_size: float, noise_bound: float) -> Iterator[Case]:
    """FPFH matches of each pair after moving its source cloud (and sensor position) far away by a random
    rigid transform; seeded by (seed, pair name, trial)."""
    for pair in pairs:
        for trial in range(trials):
            rng = np.random.default_rng([seed, 1, zlib.crc32(pair.name.encode()), trial])
            T_moved_source = random_transform(rng, MOVE_MAX_TRANSLATION)
            moved = transform_points(T_moved_source, pair.source)
            # the sensor moves with its points: normals keep facing it (see match_fpfh)
            source, target = match_fpfh(moved, pair.target, voxel_size, source_viewpoint=T_moved_source[:3, 3])
            T_truth = pair.T_target_source @ np.linalg.inv(T_moved_source)
            yield Case("real", pair.name, "fpfh", trial, source, target, T_truth, noise_bound)


def run_case(case: Case, solvers: dict[str, Solver]) -> list[dict[str, object]]:
    """Every solver on the case's correspondences: one row each. A solver that raises fails the trial."""
    T = case.T_target_source
    residuals = np.linalg.norm(transform_points(T, case.source) - case.target, axis=1)
    inlier_ratio = float(np.mean(residuals <= case.noise_bound)) if len(residuals) else 0.0
    rows = []
    for name, solver in solvers.items():
        error = ""
        start = time.perf_counter()
        try:
            T_estimate = solver(case.source, case.target, case.noise_bound)
        except Exception as exc:  # noqa: BLE001 - one failing solver must not end the benchmark
            T_estimate, error = None, f"{type(exc).__name__}: {exc}"
        elapsed = time.perf_counter() - start
        rot, trans = pose_errors(T_estimate, T) if T_estimate is not None else (float("nan"), float("nan"))
        row: dict[str, object] = {
            "part": case.part, "solver": name, "case": case.case, "outlier_kind": case.outlier_kind,
            "trial": case.trial, "n_corr": len(case.source), "inlier_ratio": inlier_ratio,
            "rot_err_deg": rot, "trans_err_m": trans, "time_s": elapsed,
        }  # fmt: skip
        for column, (max_rot, max_trans) in SUCCESS_THRESHOLDS.items():
            row[column] = int(rot <= max_rot and trans <= max_trans)
        row["error"] = error
        rows.append(row)
    return rows


def _run_part(cases: Iterator[Case], total: int, part: str, solvers: dict[str, Solver]) -> list[dict[str, object]]:
    rows = []
    for case in tqdm(cases, total=total, desc=part, unit="problem", dynamic_ncols=True):
        rows.extend(run_case(case, solvers))
    return rows


@dataclass(frozen=True)
class Settings:
    """The resolved options of one run."""

    parts: list[str]
    solvers: list[str]
    trials: int
    pair_trials: int
    voxel_size: float  # [m]
    noise_bound: float  # [m], on real pairs
    scale_sizes: list[int]
    time_limit: float  # [s]
    seed: int
    data: str | None
    out: str


def _positive(value: float, option: str) -> None:
    if not value > 0:
        raise ValueError(f"{option} must be positive, got {value}")


def _scale_sizes(text: str | None, quick: bool) -> list[int]:
    if text is None:
        return [1000] if quick else list(SCALE_SIZES)
    return parse_int_list(text, "--scale-sizes", 10, "size")


def resolve(args: argparse.Namespace) -> Settings:
    """Defaults filled in (--quick: 2 trials per rate, 1 per pair, N = 1000 only) and values checked.

    Raises:
        ValueError: an unknown part or solver, a value that is not positive, 'real' without --data.
    """
    settings = Settings(
        parts=parse_list(args.parts, PARTS, "parts"),
        solvers=parse_list(args.solvers, SOLVERS, "solvers"),
        trials=args.trials if args.trials is not None else (2 if args.quick else 40),
        pair_trials=args.pair_trials if args.pair_trials is not None else (1 if args.quick else 10),
        voxel_size=args.voxel_size,
        noise_bound=args.noise_bound if args.noise_bound is not None else args.voxel_size,
        scale_sizes=_scale_sizes(args.scale_sizes, args.quick),
        time_limit=args.time_limit,
        seed=args.seed,
        data=str(args.data) if args.data is not None else None,
        out=str(args.out if args.out is not None else default_out_dir("bench_registration")),
    )
    for option in ("trials", "pair_trials", "voxel_size", "noise_bound", "time_limit"):
        _positive(getattr(settings, option), "--" + option.replace("_", "-"))
    if "real" in settings.parts and settings.data is None:
        raise ValueError("part 'real' needs --data DIR (a folder with small_gicp/ and/or kitti07/)")
    return settings


def run(args: argparse.Namespace) -> int:
    """Run the selected parts, write CSVs, plot and settings into --out, print the tables; the exit code."""
    settings = resolve(args)
    pairs = load_pairs(Path(settings.data)) if settings.data and "real" in settings.parts else []
    out = Path(settings.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"--out {out}: {error}") from None
    solvers = {name: SOLVERS[name] for name in settings.solvers}

    rows: list[dict[str, object]] = []
    if "synthetic" in settings.parts or "real" in settings.parts:
        for solver in tqdm(solvers.values(), desc="warm-up", unit="solver", dynamic_ncols=True):
            warm_up(solver)
    if "synthetic" in settings.parts:
        total = len(OUTLIER_KINDS) * len(OUTLIER_RATES) * settings.trials
        rows += _run_part(synthetic_cases(settings.trials, settings.seed), total, "synthetic", solvers)
    if "real" in settings.parts:
        cases = real_cases(pairs, settings.pair_trials, settings.seed, settings.voxel_size, settings.noise_bound)
        rows += _run_part(cases, len(pairs) * settings.pair_trials, "real", solvers)
    scale = []
    if "scale" in settings.parts:
        scale = scale_rows(settings.solvers, settings.scale_sizes, settings.seed, settings.time_limit)

    summary = summarize(rows)
    if rows:
        write_csv(out / "trials.csv", rows, TRIAL_FIELDS)
        write_csv(out / "summary.csv", summary, SUMMARY_FIELDS)
    if scale:
        write_csv(out / "scale.csv", scale, SCALE_FIELDS)
    plot_results(rows, summary, scale, settings.solvers, out / "registration.png")
    (out / "settings.json").write_text(json.dumps(asdict(settings), indent=2) + "\n")
    print(format_tables(rows, summary, scale, settings.solvers, settings.voxel_size, settings.noise_bound))
    print(f"results in {out}")
    return 0
