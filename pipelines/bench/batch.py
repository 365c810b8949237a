"""`sandro-bench batch`: many bags and many sessions on Ray workers against one process (pipelines.batch, cluster).

slam: --bags simulated bags (`sandro-simulate`, seeds 0..N-1, --frames scans each; written once into --cache and
    reused) run by `sandro-slam`'s batch runner in five ways, each timed as a whole (wall clock):
        serial-1t   a plain loop in one new process, every run limited to one thread (`--threads-per-task 1`)
        ray1-1t     Ray with one worker, one thread per task
        ray2-1t     Ray with two workers, one thread per task
        serial      a plain loop, every run with all threads
        ray2        Ray with two workers, all threads per task
    The plain loops run in a new process each, as Ray's workers do: KISS-ICP fixes its thread count for the
    whole process at its first registration. Scaling is measured per thread: KISS-ICP alone keeps two cores busy,
    so two default tasks share the cores.
    Equal results: every run's poses.tum and loops.csv against serial-1t's (byte for byte). Memory: the peak
    resident size of the processes that ran the inputs (a Ray worker's covers every input it ran).
merge: --sessions simulated sessions of one city (SLAM of --session-frames scans each, computed once per run),
    merged with `merge_sessions` in this process, then twice on a new local Ray with two workers (the first
    time while its workers start and load the solver, then again), one thread per task throughout; the times
    and whether the transforms are equal.
Writes into --out: batch.csv (one row per way: wall time, ratio to serial-1t, equal results, peak memory),
merge.json and settings.json; prints the tables.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np

from pipelines.bench.common import default_out_dir, write_csv

WAYS = {  # name: (workers, threads per task); workers 0: a plain loop in one new process
    "serial-1t": (0, 1),
    "ray1-1t": (1, 1),
    "ray2-1t": (2, 1),
    "serial": (0, 0),
    "ray2": (2, 0),
}
FIELDS = ["way", "workers", "threads_per_task", "inputs", "done", "wall_s", "x_serial_1t", "equal_to_serial_1t",
          "peak_rss_mb"]  # fmt: skip
MERGE_ROUTES = ("A", "B", "C", "D")  # sandro-bench merge's routes, and D: A's loop started 150 m along it


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the `batch` subcommand."""
    parser.add_argument("--out", type=Path, help="results folder (default results/bench_batch/<time>)")
    parser.add_argument("--cache", type=Path, default=Path("results") / "bench_batch_bags", help="folder of the "
                        "simulated bags (written when missing; default results/bench_batch_bags)")  # fmt: skip
    parser.add_argument("--bags", type=int, default=8, help="simulated bags (default 8; 0: the merge only)")
    parser.add_argument("--frames", type=int, default=400, help="scans per bag (default 400)")
    parser.add_argument("--ways", default=",".join(WAYS), help=f"comma list of {','.join(WAYS)}")
    parser.add_argument("--sessions", type=int, default=4, help="sessions of the merge (2-4; 0: no merge)")
    parser.add_argument("--session-frames", type=int, default=400, help="scans per merge session (default 400)")


def run(args: argparse.Namespace) -> int:
    """Simulate (or reuse) the bags, run them every way, then the merge; write and print the tables."""
    from pipelines.bench.common import parse_list
    from pipelines.cluster import ray_available

    ways = parse_list(args.ways, WAYS, "ways")
    if args.bags < 0 or args.frames < 20 or args.session_frames < 20:
        raise ValueError("--bags at least 0, --frames and --session-frames at least 20")
    if args.sessions not in (0, 2, 3, 4):
        raise ValueError("--sessions: 0 (no merge) or 2-4")
    if not ray_available():
        raise ValueError("sandro-bench batch needs Ray: pip install '.[cluster]'")
    out = args.out or default_out_dir("bench_batch")
    out.mkdir(parents=True, exist_ok=True)
    (out / "settings.json").write_text(json.dumps({k: str(v) for k, v in vars(args).items()}, indent=2) + "\n")
    bags = _bags(args.cache, args.bags, args.frames)
    rows = []
    for way in ways if bags else []:
        rows.append(_run_way(way, bags, out / "runs" / way))
        reference = next((row for row in rows if row["way"] == "serial-1t"), None)
        for row in rows:
            row["x_serial_1t"] = row["wall_s"] / reference["wall_s"] if reference else float("nan")
            row["equal_to_serial_1t"] = _equal(out / "runs" / row["way"], out / "runs" / "serial-1t", bags)
        write_csv(out / "batch.csv", rows, FIELDS)
    merge = _merge(args.sessions, args.session_frames) if args.sessions else {}
    (out / "merge.json").write_text(json.dumps(merge, indent=2) + "\n")
    print(_table(rows, merge))
    print(f"results in {out}")
    return 0


def _bags(cache: Path, count: int, frames: int) -> list[Path]:
    """The simulated bags (seeds 0..count-1), written into `cache` when missing."""
    from pipelines.simulation.export import simulate

    cache.mkdir(parents=True, exist_ok=True)
    bags = []
    for seed in range(count):
        path = cache / f"drive{seed}-{frames}.bag"
        if not path.is_file():
            print(f"simulating {path} ...", flush=True)
            simulate(path, "ros1", seed=seed, frames=frames)
        bags.append(path)
    return bags


def _run_way(way: str, bags: list[Path], out: Path) -> dict:
    """Every bag run one `way`; its row."""
    from pipelines.batch import jobs_for, run_batch, run_job
    from sandro_slam import SlamConfig

    workers, threads = WAYS[way]
    jobs = jobs_for(bags, out, config=SlamConfig(), threads=threads)
    print(f"{way}: {len(bags)} bags ...", flush=True)
    tic = time.perf_counter()
    if workers == 0:  # the plain loop the Ray paths are measured against
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as process:
            rows = list(process.map(run_job, jobs))
    else:
        rows = run_batch(jobs, workers, progress=False)
    wall = time.perf_counter() - tic
    return {
        "way": way, "workers": workers, "threads_per_task": threads, "inputs": len(bags),
        "done": sum(row["status"] == "done" for row in rows), "wall_s": wall,
        "peak_rss_mb": max((row.get("peak_rss_mb") or 0.0) for row in rows),
    }  # fmt: skip


def _equal(folder: Path, reference: Path, bags: list[Path]) -> bool | None:
    """Whether every bag's poses.tum and loops.csv under `folder` equal those under `reference`; None without it."""
    if not reference.is_dir():
        return None
    for bag in bags:
        for name in ("poses.tum", "loops.csv"):
            mine, theirs = folder / bag.stem / "latest" / name, reference / bag.stem / "latest" / name
            if not (mine.is_file() and theirs.is_file()) or mine.read_bytes() != theirs.read_bytes():
                return False
    return True


def _merge(count: int, frames: int) -> dict:
    """`count` sessions of one city merged in this process and on two Ray workers, one thread per task."""
    from pipelines.bench.merge import ROUTES, _Sessions
    from pipelines.cluster import ray_map, ray_session, threads_limited
    from sandro_slam import SlamConfig, merge_sessions

    config = SlamConfig()
    routes = {**ROUTES, "D": (ROUTES["A"][0], 150.0)}
    cache = _Sessions(config)
    print(f"merge: SLAM of {count} sessions ...", flush=True)
    sessions = [cache.get(name, 0, frames, routes[name])[0] for name in MERGE_ROUTES[:count]]
    one_thread = partial(ray_map, threads=1)
    with threads_limited(1):
        tic = time.perf_counter()
        serial = merge_sessions(sessions, config)
        serial_s = time.perf_counter() - tic
        with ray_session(2, threads=1, warm_up=True):
            tic = time.perf_counter()
            cold = merge_sessions(sessions, config, one_thread)  # the workers still start and load the solver
            cold_s = time.perf_counter() - tic
            tic = time.perf_counter()
            warm = merge_sessions(sessions, config, one_thread)
            warm_s = time.perf_counter() - tic
    return {
        "sessions": count, "frames_per_session": frames, "joined": len(serial.joined), "serial_s": serial_s,
        "ray2_first_s": cold_s, "ray2_again_s": warm_s, "x_serial_first": cold_s / serial_s,
        "x_serial_again": warm_s / serial_s, "equal_transforms": _same_transforms(serial, cold, warm),
        "serial_timings_s": serial.timings, "ray2_first_timings_s": cold.timings, "ray2_again_timings_s": warm.timings,
    }  # fmt: skip


def _same_transforms(first, *others) -> bool:
    """Whether merge results joined the same sessions with bit-identical transforms."""
    T = first.T_merged_session
    return all(
        other.T_merged_session.keys() == T.keys() and all(np.array_equal(T[k], other.T_merged_session[k]) for k in T)
        for other in others
    )


def _table(rows: list[dict], merge: dict) -> str:
    lines = [f"{'way':<11}{'workers':>8}{'threads':>8}{'done':>6}{'wall s':>9}{'x serial-1t':>12}{'equal':>7}"
             f"{'peak MB':>9}"]  # fmt: skip
    for row in rows:
        lines.append(
            f"{row['way']:<11}{row['workers']:>8}{row['threads_per_task']:>8}{row['done']:>6}{row['wall_s']:>9.1f}"
            f"{row['x_serial_1t']:>12.2f}{str(row['equal_to_serial_1t']):>7}{row['peak_rss_mb']:>9.0f}"
        )
    if merge:
        lines.append(
            f"merge of {merge['sessions']} sessions ({merge['joined']} joined), one thread per task: "
            f"{merge['serial_s']:.1f} s in process; on 2 Ray workers {merge['ray2_first_s']:.1f} s the first time "
            f"({merge['x_serial_first']:.2f}x), {merge['ray2_again_s']:.1f} s again ({merge['x_serial_again']:.2f}x); "
            f"equal transforms: {merge['equal_transforms']}"
        )
    return "\n".join(lines)
