"""`sandro-bench posegraph`: the robust back end on real pose graphs with injected outlier loops.

Per graph (every *.g2o in --data; 2D EDGE_SE2 or 3D EDGE_SE3:QUAT, read with gtsam.readG2o plus a prior on
the first pose; edges between consecutive ids are the odometry, duplicates included; where it has gaps, each
further chain gets a weak prior on its first pose; a graph without such edges is refused):
    reference: Levenberg-Marquardt on the clean graph from the file's initial values and from the chordal
        relaxation (`sandro_slam.chordal`; some files hold identity or random vertices, from which LM stops in
        a local minimum), the solution of lower cost (gtsam error, 0.5 * sum of squared whitened residuals);
        its time is the shorter of the two starts' that reach that cost (within `REFERENCE_COST_TOL`).
        start_spread: pose_rel (below) of the other start's solution against it: where that is large at
        nearly the same cost, the data leave the poses free along a flat valley (ais2klinik: 1.6 %), and a
        result's pose_rel up to it says where LM stopped, not which loops were kept.
    info scale: every edge's information matrix multiplied by a factor (default 1: as published; 'auto':
        1 / the reference's a-posteriori variance factor 2 * cost / redundancy, so whitened residuals get
        unit variance). No optimum moves; for GNC it is the same as dividing its inlier threshold by it.
    corruption: per rate, rate % as many outlier loops as the graph has real loops (edges between
        non-consecutive ids), between random pose pairs at least two ids apart, each measuring a random
        relative pose (translation uniform in a ball of 5 m, rotation about a random axis by up to
        +-30 deg; 2D: a disc and a yaw) with the noise model of a typical real loop (median log-det of
        the information). Seeded by (seed, graph name, rate).
    methods: gnc_tls (sandro_slam's default back end: `sandro_slam.robust_backend.robust_optimize` with
        `noise_scale: estimated`, prior and odometry as known inliers), gnc_tls_given and gnc_gm (TLS and
        Geman-McClure with the covariances as given), lm (plain), huber (k = 1.345) and cauchy (k = 2.3849) on
        every loop edge only; k are the 95 %-efficiency constants, on whitened residuals.
    metrics against the reference: translation RMSE and max [m] (no alignment: the prior fixes the first
        pose), rotation RMSE [deg], pose_rel = translation RMSE / trajectory scale (RMS distance of the
        reference positions from their centroid), cost_rel = |clean cost at the result - reference cost| /
        reference cost (none where the measurements are exact: a clean cost of numerically 0, the reference's
        variance factor below `EXACT_VARIANCE_FACTOR`); for GNC the precision and recall of rejecting the
        injected loops (weight < 0.5) and the number of real loops rejected. tls_rel: the result's truncated
        least squares cost on the corrupted graph (every squared whitened error, each loop's truncated at its
        inlier threshold: the chi-square quantile of its dimension at the back end's inlier probability,
        covariances as published) against the clean optimum's, signed: at or below 0 the result is as good a
        TLS solution as the clean optimum, and the real loops it rejects are ones their published covariances
        call outliers. within_1pct: pose_rel <= 1 % and cost_rel (where there is one) <= 1 %. time_s and
        time_x_ref: the run's time and its ratio to the reference's (the back end's compiled kernels are loaded
        before the first run: `load_kernels`).
    profile (--profile): each run under cProfile (its time_s then includes the profiler's overhead), and per run
        where its time went: every function of sandro_slam, and gtsam's nonlinear solves (`gtsam.optimize`: one
        call per Levenberg-Marquardt or GNC run), with its calls and cumulative time, those at `PROFILE_SHARE` of
        the run or more.
Writes into --out: results.csv (one row per graph, info scale, rate, initial values and method; rewritten after
every run, so a long run can be read while it goes), reference.csv, posegraph.png (translation RMSE per method
and rate, one panel per graph), posegraph_time.png (time against graph size), settings.json and, with --profile,
profile.csv.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import math
import pstats
import time
import zlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import gtsam
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the backend
import numpy as np  # noqa: E402
from scipy.stats import chi2  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pipelines.bench.common import default_out_dir, parse_int_list, parse_list, write_csv  # noqa: E402
from sandro_core.geometry import rotation_angle
from sandro_slam.chordal import chordal_values  # noqa: E402
from sandro_slam.config import GraphConfig  # noqa: E402
from sandro_slam.covariance import FactorCovariances  # noqa: E402
from sandro_slam.robust_backend import robust_optimize, tls_cost  # noqa: E402

BACK_ENDS = {  # GNC methods: the robust back end's configuration
    "gnc_tls": GraphConfig(robust="gnc_tls"),
    "gnc_tls_given": GraphConfig(robust="gnc_tls", noise_scale="given"),
    "gnc_gm": GraphConfig(robust="gnc_gm", noise_scale="given"),
}
METHODS = (*BACK_ENDS, "lm", "huber", "cauchy")
INITS = ("file", "odometry")  # initial values of the corrupted graph: the file's, or the odometry chain
KERNELS = {"huber": 1.345, "cauchy": 2.3849}  # mEstimator constants on whitened residuals
PRIOR_SIGMA = 1e-3  # [rad], [m], on the first pose
CHAIN_PRIOR_SIGMA = 1e3  # [rad], [m], on the first pose of every further odometry chain
OUTLIER_MAX_TRANSLATION = 5.0  # [m]
OUTLIER_MAX_ANGLE_DEG = 30.0
QUICK_POSES = 200  # --quick keeps the first graph's first poses only
REFERENCE_COST_TOL = 1e-5  # relative cost within which a start of the reference reaches the clean optimum
TARGET = 0.01  # pose_rel and cost_rel of a robust result within 1 % of the reference
EXACT_VARIANCE_FACTOR = 1e-12  # a clean optimum's variance factor below which its measurements are exact: cost 0
PROFILE_SHARE = 0.01  # --profile: functions of at least this share of a run's time are listed
REFERENCE_FIELDS = [
    "graph", "info_scale", "dim", "n_poses", "n_chains", "n_odometry", "n_loops", "cost_clean", "variance_factor",
    "scale_m", "time_s", "start", "cost_file", "time_file_s", "cost_chordal", "time_chordal_s", "start_spread",
]  # fmt: skip
RESULT_FIELDS = [
    "graph", "info_scale", "rate_pct", "n_outliers", "init", "method", "trans_rmse_m", "trans_max_m", "rot_rmse_deg",
    "pose_rel", "cost", "cost_rel", "precision", "recall", "real_rejected", "tls_rel", "time_s", "time_x_ref",
    "within_1pct", "error",
]  # fmt: skip
PROFILE_FIELDS = [
    "graph", "info_scale", "rate_pct", "n_outliers", "init", "method", "function", "calls", "time_s", "share",
]  # fmt: skip


@dataclass
class Problem:
    """A pose graph split into its parts; factors are BetweenFactorPose2/Pose3 as gtsam.readG2o made them."""

    name: str
    is3d: bool
    keys: list[int]  # sorted pose ids
    priors: list[gtsam.NonlinearFactor]  # on the first pose; weak ones on the first pose of every further chain
    odometry: list[gtsam.NonlinearFactor]  # edges between consecutive ids: known inliers
    loops: list[gtsam.NonlinearFactor]  # every other edge: real loops
    initial: gtsam.Values  # the file's vertices (readG2o chains the edges where a file has none)


@dataclass
class Reference:
    """The clean optimum of a problem."""

    values: gtsam.Values
    cost: float
    T: np.ndarray  # (N, 4, 4) T_world_pose in key order
    scale: float  # [m], RMS distance of the positions from their centroid
    variance_factor: float  # 2 * cost / redundancy: 1 when the noise models match the residuals


def _prior(key: int, pose: gtsam.Pose2 | gtsam.Pose3, is3d: bool, sigma: float) -> gtsam.NonlinearFactor:
    if is3d:
        return gtsam.PriorFactorPose3(key, pose, gtsam.noiseModel.Isotropic.Sigma(6, sigma))
    return gtsam.PriorFactorPose2(key, pose, gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def _pose(values: gtsam.Values, key: int, is3d: bool) -> gtsam.Pose2 | gtsam.Pose3:
    return values.atPose3(key) if is3d else values.atPose2(key)


def _is_2d(path: Path) -> bool:
    """True when the first tag of the file is a 2D one (EDGE_SE2 / VERTEX_SE2)."""
    with path.open() as handle:
        for line in handle:
            if line.strip():
                return line.split()[0].endswith("SE2")
    raise ValueError(f"{path}: empty file")


def load_problem(path: Path, max_poses: int | None = None) -> Problem:
    """Read a g2o file (2D or 3D) and split its edges; `max_poses` keeps the first poses and their edges.

    Edges between consecutive ids are the odometry (duplicates included), every other edge a loop. Where the
    odometry has gaps, the graph is several chains that only loops join (sessions): each chain after the first
    gets a weak prior (`CHAIN_PRIOR_SIGMA`) at its first pose, so that it stays determined when the robust back
    end rejects every loop to it; the prior does not move the clean optimum measurably.

    Raises:
        ValueError: gtsam cannot read the file, or fewer than 3 poses, or no edge between consecutive ids.
    """
    is3d = not _is_2d(path)
    try:
        graph, initial = gtsam.readG2o(str(path), is3d)
    except RuntimeError as error:
        raise ValueError(f"{path}: {error}") from None
    keys = sorted(initial.keys())[:max_poses]
    kept = set(keys)
    odometry, loops = [], []
    for i in range(graph.size()):
        factor = graph.at(i)
        a, b = factor.keys()
        if a in kept and b in kept:
            (odometry if abs(a - b) == 1 else loops).append(factor)
    if len(keys) < 3 or not odometry:
        raise ValueError(f"{path}: needs at least 3 poses and an odometry chain (edges between consecutive ids)")
    chained = {min(factor.keys()) for factor in odometry}
    starts = [keys[0]] + [
        key for previous, key in zip(keys, keys[1:]) if previous not in chained or key != previous + 1
    ]
    values = gtsam.Values()
    for key in keys:
        values.insert(key, _pose(initial, key, is3d))
    priors = [_prior(key, _pose(initial, key, is3d), is3d, PRIOR_SIGMA if key == keys[0] else CHAIN_PRIOR_SIGMA)
              for key in starts]  # fmt: skip
    return Problem(path.stem, is3d, keys, priors, odometry, loops, values)


def odometry_initial(problem: Problem) -> gtsam.Values:
    """Initial values from the file's first pose of each chain composed along the odometry edges."""
    steps = {}
    for factor in problem.odometry:
        a, b = factor.keys()
        steps[min(a, b)] = factor.measured() if b > a else factor.measured().inverse()
    values = gtsam.Values()
    pose = None
    for key in problem.keys:
        step = steps.get(key - 1)
        pose = _pose(problem.initial, key, problem.is3d) if pose is None or step is None else pose.compose(step)
        values.insert(key, pose)
    return values


def build_graph(
    problem: Problem, outliers: list[gtsam.NonlinearFactor]
) -> tuple[gtsam.NonlinearFactorGraph, list[int]]:
    """Priors, odometry, real loops, then `outliers`; returns the graph and its known-inlier indices."""
    graph = gtsam.NonlinearFactorGraph()
    for factor in [*problem.priors, *problem.odometry, *problem.loops, *outliers]:
        graph.add(factor)
    return graph, list(range(len(problem.priors) + len(problem.odometry)))


def typical_loop_noise(problem: Problem) -> gtsam.noiseModel.Base:
    """The noise model of the real loop with the median log-determinant of its information matrix
    (of an odometry edge if the graph has no loops)."""
    factors = problem.loops or problem.odometry
    logdets = [np.linalg.slogdet(factor.noiseModel().information())[1] for factor in factors]
    return factors[int(np.argsort(logdets)[len(logdets) // 2])].noiseModel()


def _random_relative_pose(rng: np.random.Generator, is3d: bool) -> gtsam.Pose2 | gtsam.Pose3:
    """Translation uniform in a ball (disc) of OUTLIER_MAX_TRANSLATION, rotation by up to
    OUTLIER_MAX_ANGLE_DEG about a random axis (yaw)."""
    dim = 3 if is3d else 2
    direction = rng.normal(size=dim)
    t = direction / np.linalg.norm(direction) * OUTLIER_MAX_TRANSLATION * rng.random() ** (1.0 / dim)
    angle = np.radians(rng.uniform(-OUTLIER_MAX_ANGLE_DEG, OUTLIER_MAX_ANGLE_DEG))
    if not is3d:
        return gtsam.Pose2(t[0], t[1], angle)
    axis = rng.normal(size=3)
    return gtsam.Pose3(gtsam.Rot3.Expmap(axis / np.linalg.norm(axis) * angle), t)


def inject_outliers(problem: Problem, rate_pct: int, seed: int) -> list[gtsam.NonlinearFactor]:
    """rate_pct % as many random loop edges as the graph has real loops, seeded by (seed, name, rate)."""
    rng = np.random.default_rng([seed, zlib.crc32(problem.name.encode()), rate_pct])
    count = round(rate_pct / 100.0 * len(problem.loops))
    noise = typical_loop_noise(problem)
    between = gtsam.BetweenFactorPose3 if problem.is3d else gtsam.BetweenFactorPose2
    keys = np.asarray(problem.keys)
    outliers = []
    while len(outliers) < count:
        a, b = rng.choice(keys, size=2, replace=False)
        if abs(int(a) - int(b)) > 1:
            outliers.append(between(int(a), int(b), _random_relative_pose(rng, problem.is3d), noise))
    return outliers


def _robust_loops(graph: gtsam.NonlinearFactorGraph, first_loop: int, method: str) -> gtsam.NonlinearFactorGraph:
    """A copy of `graph` whose factors from index `first_loop` on carry the method's M-estimator."""
    estimator = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[method]
    robust = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if i >= first_loop:
            model = gtsam.noiseModel.Robust.Create(estimator.Create(KERNELS[method]), factor.noiseModel())
            factor = type(factor)(*factor.keys(), factor.measured(), model)
        robust.add(factor)
    return robust


def optimize(
    method: str, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, known_inliers: list[int]
) -> tuple[gtsam.Values, np.ndarray | None]:
    """Run one method; returns the values and, for GNC, the weight per factor."""
    if method in BACK_ENDS:
        return robust_optimize(graph, initial, known_inliers, BACK_ENDS[method])
    if method in KERNELS:
        graph = _robust_loops(graph, len(known_inliers), method)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize(), None


def load_kernels() -> None:
    """The robust back end's covariance kernels run once on a four-pose chain, for one of its factors and for a
    loop between its ends that it does not hold (forward substitution): numba loads their compiled code at a
    process's first call (0.2-0.3 s), which would otherwise count in the first graph's time."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), noise))
    values.insert(0, gtsam.Pose2())
    for key in (1, 2, 3):
        graph.add(gtsam.BetweenFactorPose2(key - 1, key, gtsam.Pose2(1.0, 0.0, 0.0), noise))
        values.insert(key, gtsam.Pose2(float(key), 0.0, 0.0))
    loop = gtsam.BetweenFactorPose2(0, 3, gtsam.Pose2(3.0, 0.0, 0.0), noise)
    FactorCovariances(graph, values).mahalanobis([graph.at(2), loop], values)


def pose_matrices(values: gtsam.Values, keys: list[int], is3d: bool) -> np.ndarray:
    """(N, 4, 4) T_world_pose in key order; 2D poses lifted to the plane z = 0."""
    if is3d:
        return np.stack([values.atPose3(key).matrix() for key in keys])
    T = np.tile(np.eye(4), (len(keys), 1, 1))
    for i, key in enumerate(keys):
        M = values.atPose2(key).matrix()
        T[i, :2, :2], T[i, :2, 3] = M[:2, :2], M[:2, 2]
    return T


def reference(problem: Problem) -> tuple[Reference, float, dict[str, object]]:
    """The clean optimum (LM to tight tolerances from the file's initial values and from the chordal relaxation:
    the solution of lower cost), the reference time [s] (the shorter time of the starts that reach that cost within
    `REFERENCE_COST_TOL`), and per start its cost and time plus the start of the reference time."""
    graph, _ = build_graph(problem, [])
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    params.setMaxIterations(500)
    solutions: dict[str, tuple[gtsam.Values, float]] = {}
    for start_name in ("file", "chordal"):
        start = time.perf_counter()
        initial = problem.initial if start_name == "file" else chordal_values(graph, problem.initial)
        if initial is None:
            continue
        values = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        solutions[start_name] = values, time.perf_counter() - start
    costs = {name: graph.error(values) for name, (values, _) in solutions.items()}
    best = min(costs, key=costs.__getitem__)
    reached = [name for name in solutions if costs[name] <= costs[best] * (1.0 + REFERENCE_COST_TOL)]
    fastest = min(reached, key=lambda name: solutions[name][1])
    details: dict[str, object] = {"start": fastest}
    for name, (_, elapsed) in solutions.items():
        details[f"cost_{name}"], details[f"time_{name}_s"] = costs[name], elapsed
    ref = _reference_at(problem, solutions[best][0])
    other = [values for name, (values, _) in solutions.items() if name != best]
    details["start_spread"] = compare(other[0], problem, ref)["pose_rel"] if other else math.nan
    return ref, solutions[fastest][1], details


def _reference_at(problem: Problem, values: gtsam.Values) -> Reference:
    graph, _ = build_graph(problem, [])
    T = pose_matrices(values, problem.keys, problem.is3d)
    positions = T[:, :3, 3]
    scale = float(np.sqrt(np.mean(np.sum((positions - positions.mean(axis=0)) ** 2, axis=1))))
    redundancy = sum(graph.at(i).dim() for i in range(graph.size())) - (6 if problem.is3d else 3) * len(problem.keys)
    cost = graph.error(values)
    return Reference(values, cost, T, scale, 2.0 * cost / redundancy)


def scale_information(problem: Problem, ref: Reference, scale: float) -> tuple[Problem, Reference]:
    """The problem with every edge's information multiplied by `scale`, and its reference (the same
    optimum; cost times `scale`)."""

    def scaled(factor: gtsam.NonlinearFactor) -> gtsam.NonlinearFactor:
        model = gtsam.noiseModel.Gaussian.Information(factor.noiseModel().information() * scale)
        return type(factor)(*factor.keys(), factor.measured(), model)

    problem = replace(problem, odometry=[scaled(f) for f in problem.odometry], loops=[scaled(f) for f in problem.loops])
    return problem, _reference_at(problem, ref.values)


def compare(values: gtsam.Values, problem: Problem, ref: Reference) -> dict[str, float]:
    """Pose and cost errors of `values` against the reference (see the module docstring)."""
    T = pose_matrices(values, problem.keys, problem.is3d)
    translation = np.linalg.norm(T[:, :3, 3] - ref.T[:, :3, 3], axis=1)
    R = np.einsum("nji,njk->nik", T[:, :3, :3], ref.T[:, :3, :3])
    angles = rotation_angle(R)
    clean, _ = build_graph(problem, [])
    cost = clean.error(values)
    rmse = float(np.sqrt(np.mean(translation**2)))
    return {
        "trans_rmse_m": rmse, "trans_max_m": float(translation.max()),
        "rot_rmse_deg": float(np.degrees(np.sqrt(np.mean(angles**2)))), "pose_rel": rmse / ref.scale,
        "cost": cost,
        "cost_rel": abs(cost - ref.cost) / ref.cost if ref.variance_factor > EXACT_VARIANCE_FACTOR else math.nan,
    }  # fmt: skip


def rejection(weights: np.ndarray, n_known: int, n_real: int) -> dict[str, float | int]:
    """Precision and recall of rejecting the injected loops (weight < 0.5; they follow the real loops)."""
    rejected = weights[n_known:] < 0.5
    real_rejected = int(rejected[:n_real].sum())
    true_rejected = int(rejected[n_real:].sum())
    n_outliers = len(rejected) - n_real
    return {
        "precision": true_rejected / (true_rejected + real_rejected) if rejected.any() else math.nan,
        "recall": true_rejected / n_outliers if n_outliers else math.nan,
        "real_rejected": real_rejected,
    }


def run_one(
    problem: Problem,
    ref: Reference,
    method: str,
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    known: list[int],
    profiler: cProfile.Profile | None = None,
) -> dict[str, object]:
    """One optimisation of the corrupted graph: its metrics and time [s]; an exception becomes `error`. With
    `profiler`, the optimisation runs under it."""
    start = time.perf_counter()
    try:
        if profiler is None:
            values, weights = optimize(method, graph, initial, known)
        else:
            values, weights = profiler.runcall(optimize, method, graph, initial, known)
    except RuntimeError as exc:
        return {"time_s": time.perf_counter() - start, "within_1pct": 0, "error": f"{type(exc).__name__}: {exc}"}
    row: dict[str, object] = {"time_s": time.perf_counter() - start, **compare(values, problem, ref)}
    if weights is not None:
        row.update(rejection(weights, len(known), len(problem.loops)))
    # the loops (every factor but the known inliers, which come first) at the back end's inlier thresholds
    limits = chi2.ppf(GraphConfig().inlier_probability, [graph.at(i).dim() for i in range(len(known), graph.size())])
    reference_tls = tls_cost(graph, ref.values, known, limits)
    row["tls_rel"] = (tls_cost(graph, values, known, limits) - reference_tls) / reference_tls
    row["within_1pct"] = int(row["pose_rel"] <= TARGET and not row["cost_rel"] > TARGET)  # NaN: exact measurements
    row["error"] = ""
    return row


def profile_rows(profiler: cProfile.Profile, total: float) -> list[dict[str, object]]:
    """Where a profiled run of `total` seconds went: per function of sandro_slam (file:line(name)) and gtsam's
    nonlinear solves (`gtsam.optimize`) of at least `PROFILE_SHARE` of it, its calls and cumulative time [s], the
    longest first."""
    rows = []
    for (path, line, name), (_, calls, _, cumulative, _) in pstats.Stats(profiler).stats.items():
        if "/sandro_slam/" in path:
            function = f"{Path(path).name}:{line}({name})"  # pstats' notation
        elif name == "<built-in method gtsam.gtsam.optimize>":
            function = "gtsam.optimize"
        else:
            continue
        if cumulative >= PROFILE_SHARE * total:
            rows.append({"function": function, "calls": calls, "time_s": cumulative, "share": cumulative / total})
    return sorted(rows, key=lambda row: -row["time_s"])


@dataclass(frozen=True)
class Settings:
    """The resolved options of one run."""

    data: str
    graphs: list[str]
    rates: list[int]  # [%] of the real loop count
    methods: list[str]
    inits: list[str]
    info_scales: list[str]  # positive numbers or 'auto'
    max_poses: int | None
    seed: int
    profile: bool
    out: str


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `posegraph` subcommand."""
    parser.add_argument("--data", type=Path, required=True, help="folder of .g2o pose graphs (e.g. se_sync)")
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_posegraph/<time>)")
    parser.add_argument("--graphs", help="comma list of graph names (file stems; default every .g2o in --data)")
    parser.add_argument("--rates", default="10,30,50", help="outlier loops in %% of the real loops (10,30,50)")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma list of {','.join(METHODS)}")
    parser.add_argument("--init", default="file", help="initial values: comma list of file,odometry (file)")
    parser.add_argument(
        "--info-scale", default="1", help="comma list of factors on every edge's information, or 'auto' (1)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the injected outliers (0)")
    parser.add_argument("--quick", action="store_true", help=f"first graph only, its first {QUICK_POSES} poses")
    parser.add_argument(
        "--profile", action="store_true", help="profile every run: where its time went, into profile.csv"
    )


def _rates(text: str) -> list[int]:
    return list(dict.fromkeys(parse_int_list(text, "--rates", 0, "rate")))


def _info_scales(text: str) -> list[str]:
    scales = [scale.strip() for scale in text.split(",") if scale.strip()]
    for scale in scales:
        try:
            ok = scale == "auto" or float(scale) > 0
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(f"--info-scale {scale!r}: expected positive numbers or 'auto'")
    return list(dict.fromkeys(scales)) or ["1"]


def resolve(args: argparse.Namespace) -> Settings:
    """Defaults filled in and values checked.

    Raises:
        ValueError: a missing --data folder or one without .g2o files, an unknown graph, method, init or
            info scale, a bad rate.
    """
    if not args.data.is_dir():
        raise ValueError(f"--data {args.data}: no such folder")
    available = sorted(path.stem for path in args.data.glob("*.g2o"))
    if not available:
        raise ValueError(f"--data {args.data}: holds no .g2o file")
    graphs = parse_list(args.graphs, available, "graphs") if args.graphs else available
    return Settings(
        data=str(args.data),
        graphs=graphs[:1] if args.quick else graphs,
        rates=_rates(args.rates),
        methods=parse_list(args.methods, METHODS, "methods"),
        inits=parse_list(args.init, INITS, "init"),
        info_scales=_info_scales(args.info_scale),
        max_poses=QUICK_POSES if args.quick else None,
        seed=args.seed,
        profile=args.profile,
        out=str(args.out if args.out is not None else default_out_dir("bench_posegraph")),
    )


def _cell(value: object, spec: str) -> str:
    return "-" if value in ("", None) or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def format_table(references: list[dict[str, object]], rows: list[dict[str, object]]) -> str:
    """Text tables: the references, then one line per graph, info scale, rate, init and method."""
    lines = [
        "reference (clean graph, LM from the file's initial values and from the chordal relaxation: the lower cost,"
        " the faster start to it; variance factor = 2 cost / redundancy; spread: pose_rel of the other start)",
        f"{'graph':<16}{'info x':>8} {'dim':>4}{'poses':>7}{'chains':>7}{'odom':>7}{'loops':>7}{'cost':>13}"
        f"{'var.f.':>10}{'scale m':>9}{'time s':>8} {'start':<8}{'file: cost':>13}{'time s':>8}{'spread%':>9}",
    ]
    for ref in references:
        lines.append(
            f"{ref['graph']:<16}{ref['info_scale']:>8.3g} {ref['dim']:>4}{ref['n_poses']:>7}{ref['n_chains']:>7}"
            f"{ref['n_odometry']:>7}"
            f"{ref['n_loops']:>7}{ref['cost_clean']:>13.6g}{ref['variance_factor']:>10.3g}{ref['scale_m']:>9.1f}"
            f"{ref['time_s']:>8.2f} {ref['start']:<8}{ref['cost_file']:>13.6g}{ref['time_file_s']:>8.2f}"
            f"{_cell(100 * ref['start_spread'], '.3g'):>9}"
        )
    lines += [
        "",
        "corrupted graphs (pose_rel = rmse / scale, cost_rel: clean cost vs the reference's; prec/rec: "
        "rejection of the injected loops; tls_rel: truncated least squares cost vs the clean optimum's; ok: "
        "pose_rel and cost_rel <= 1 %)",
        f"{'graph':<16}{'info x':>8}{'rate%':>6}{'n_out':>6} {'init':<9}{'method':<8}{'rmse m':>10}"
        f"{'max m':>10}{'rot deg':>9}{'pose_rel%':>10}{'cost_rel%':>11}{'prec':>6}{'rec':>6}{'real_rej':>9}"
        f"{'tls_rel%':>10}{'time s':>8}{'x ref':>7}  ok",
    ]
    for r in rows:
        label = (
            f"{r['graph']:<16}{r['info_scale']:>8.3g}{r['rate_pct']:>6}{r['n_outliers']:>6} "
            f"{r['init']:<9}{r['method']:<8}"
        )
        if r["error"]:
            lines.append(f"{label}  error: {r['error']}")
            continue
        lines.append(
            f"{label}{r['trans_rmse_m']:>10.3g}{r['trans_max_m']:>10.3g}{r['rot_rmse_deg']:>9.3g}"
            f"{100 * r['pose_rel']:>10.3g}{_cell(100 * r['cost_rel'], '.3g'):>11}{_cell(r.get('precision'), '.2f'):>6}"
            f"{_cell(r.get('recall'), '.2f'):>6}{_cell(r.get('real_rejected'), 'd'):>9}"
            f"{100 * r['tls_rel']:>10.2g}{r['time_s']:>8.2f}"
            f"{r['time_x_ref']:>7.1f}"
            f"  {'yes' if r['within_1pct'] else 'no'}"
        )
    return "\n".join(lines)


def plot(rows: list[dict[str, object]], references: list[dict[str, object]], path: Path) -> None:
    """Translation RMSE [m] per method (and init) and outlier rate, one log-scale panel per graph and info scale;
    the dashed line is 1 % of the trajectory scale."""
    fig, axes = plt.subplots(1, len(references), figsize=(5.5 * len(references), 4.2), squeeze=False)
    for ax, ref in zip(axes[0], references):
        mine = [row for row in rows if (row["graph"], row["info_scale"]) == (ref["graph"], ref["info_scale"])]
        rates = list(dict.fromkeys(row["rate_pct"] for row in mine))
        series = list(dict.fromkeys((row["method"], row["init"]) for row in mine))
        width = 0.8 / max(len(series), 1)
        for j, (method, init) in enumerate(series):
            heights = [
                next((float(r.get("trans_rmse_m", math.nan)) for r in mine
                      if (r["method"], r["init"], r["rate_pct"]) == (method, init, rate)), math.nan)
                for rate in rates
            ]  # fmt: skip
            label = method if len({i for _, i in series}) == 1 else f"{method} ({init})"
            ax.bar(np.arange(len(rates)) + (j - (len(series) - 1) / 2) * width, heights, width, label=label)
        ax.axhline(TARGET * float(ref["scale_m"]), color="k", linestyle="--", linewidth=1, label="1 % of scale")
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(rates)), [f"{rate} %" for rate in rates])
        ax.set_xlabel("injected outlier loops (% of real loops)")
        ax.set_ylabel("translation RMSE vs clean optimum [m]")
        ax.set_title(
            f"{ref['graph']}, information x {ref['info_scale']:.3g}\n({ref['n_poses']} poses, {ref['n_loops']} loops)"
        )
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_times(rows: list[dict[str, object]], references: list[dict[str, object]], path: Path) -> None:
    """Time [s] against graph size (poses), log-log: one series per method and outlier rate, the clean
    least-squares reference in black, the 60 s mark dashed."""
    fig, ax = plt.subplots(figsize=(7, 4.8))
    poses = {(r["graph"], r["info_scale"]): r["n_poses"] for r in references}
    series = list(dict.fromkeys((row["method"], row["init"], row["rate_pct"]) for row in rows))
    markers = "os^vD<>p*h"
    for j, (method, init, rate) in enumerate(series):
        mine = [r for r in rows if (r["method"], r["init"], r["rate_pct"]) == (method, init, rate) and not r["error"]]
        mine.sort(key=lambda r: poses[(r["graph"], r["info_scale"])])
        label = f"{method} ({init}), {rate} %" if len({s[1] for s in series}) > 1 else f"{method}, {rate} %"
        ax.plot([poses[(r["graph"], r["info_scale"])] for r in mine], [r["time_s"] for r in mine],
                marker=markers[j % len(markers)], linewidth=1, label=label)  # fmt: skip
    clean = sorted((r["n_poses"], r["time_s"]) for r in references)
    ax.plot(*zip(*clean), "k-", marker="x", linewidth=1.5, label="clean least squares")
    ax.axhline(60.0, color="k", linestyle="--", linewidth=1, label="60 s")
    for ref in references:
        ax.annotate(ref["graph"], (ref["n_poses"], ref["time_s"]), fontsize=7, textcoords="offset points",
                    xytext=(0, -10), ha="center")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("poses")
    ax.set_ylabel("time [s]")
    ax.set_title("robust pose-graph optimisation time against graph size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """Run every graph, info scale, rate, init and method; write CSVs, plot and settings into --out; print the
    tables."""
    settings = resolve(args)
    problems = [load_problem(Path(settings.data) / f"{name}.g2o", settings.max_poses) for name in settings.graphs]
    out = Path(settings.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"--out {out}: {error}") from None
    (out / "settings.json").write_text(json.dumps(asdict(settings), indent=2) + "\n")

    load_kernels()
    references, rows, profiles = [], [], []
    runs = len(settings.info_scales) * len(settings.rates) * len(settings.inits) * len(settings.methods)
    with tqdm(total=len(problems) * runs, desc="posegraph", unit="run", dynamic_ncols=True) as progress:
        for file_problem in problems:
            file_ref, elapsed, details = reference(file_problem)
            initials = {"file": file_problem.initial, "odometry": odometry_initial(file_problem)}
            for text in settings.info_scales:
                info_scale = 1.0 / file_ref.variance_factor if text == "auto" else float(text)
                problem, ref = scale_information(file_problem, file_ref, info_scale)
                references.append({
                    "graph": problem.name, "info_scale": info_scale, "dim": 3 if problem.is3d else 2,
                    "n_poses": len(problem.keys), "n_chains": len(problem.priors), "n_odometry": len(problem.odometry),
                    "n_loops": len(problem.loops),
                    "cost_clean": ref.cost, "variance_factor": ref.variance_factor, "scale_m": ref.scale,
                    "time_s": elapsed, **details,
                })  # fmt: skip
                write_csv(out / "reference.csv", references, REFERENCE_FIELDS)
                for rate in settings.rates:
                    graph, known = build_graph(problem, inject_outliers(problem, rate, settings.seed))
                    for init in settings.inits:
                        for method in settings.methods:
                            progress.set_postfix_str(f"{problem.name} x{info_scale:.3g} {rate}% {init} {method}")
                            labels = {
                                "graph": problem.name, "info_scale": info_scale, "rate_pct": rate,
                                "n_outliers": graph.size() - len(known) - len(problem.loops),
                                "init": init, "method": method,
                            }  # fmt: skip
                            profiler = cProfile.Profile() if settings.profile else None
                            row = {**labels, **run_one(problem, ref, method, graph, initials[init], known, profiler)}
                            rows.append({**row, "time_x_ref": row["time_s"] / elapsed})
                            write_csv(out / "results.csv", rows, RESULT_FIELDS)  # so far: a long run can be read
                            if profiler is not None:
                                profiles += [{**labels, **p} for p in profile_rows(profiler, row["time_s"])]
                                write_csv(out / "profile.csv", profiles, PROFILE_FIELDS)
                            progress.update()

    plot(rows, references, out / "posegraph.png")
    plot_times(rows, references, out / "posegraph_time.png")
    print(format_table(references, rows))
    print(f"results in {out}")
    return 0
