"""Scale part of `sandro-bench registration`: time and peak memory per solver and number of correspondences.

Each (solver, N) is measured in a fresh process (multiprocessing, spawn), because allocations made by
numba or Open3D are invisible to tracemalloc. The process imports everything, warms the solver up on a
tiny problem (JIT compilation) and builds its problem (N correspondences, 90 % uniform outliers). Then
freed heap memory goes back to the OS (glibc `malloc_trim`) and the peak-RSS mark is lowered to the
current RSS (Linux `clear_refs`); peak memory = peak RSS after the calls - peak RSS before them.
The peak RSS is VmHWM of /proc/self/status, the figure ru_maxrss is made from: ru_maxrss itself also
keeps the peak seen when any thread of a thread pool exited, which the reset does not lower. Where a
step is unavailable (not Linux) ru_maxrss is used and the figure is a lower bound.
Time is the median of 3 calls, or of 1 when 3 would exceed the time limit; a call still running at
the time limit is stopped and the size marked as a timeout.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import multiprocessing
import os
import resource
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import cast

import numpy as np
from tqdm import tqdm

from pipelines.bench.solvers import SOLVERS, warm_up
from pipelines.evaluation import pose_errors
from pipelines.simulation.correspondences import make_problem

SCALE_SIZES = (1_000, 10_000, 100_000)
SCALE_OUTLIER_RATE = 0.9
REPEATS = 3
SETUP_TIMEOUT = 300.0  # [s] for imports, warm-up and problem generation in the worker
SCALE_FIELDS = [
    "part", "solver", "n", "outlier_rate", "status", "runs", "time_median_s", "peak_memory_mb",
    "rot_err_deg", "trans_err_m", "success_10deg_1m",
]  # fmt: skip


def _reset_peak_rss() -> None:
    """Hand freed heap memory back to the OS (glibc `malloc_trim`, so that reusing it counts again), then
    lower this process's peak-RSS mark to its current RSS (Linux >= 4.0). Each step is skipped where
    unavailable."""
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_rss_mb() -> float:
    """This process's peak resident set size [MB]."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _worker(conn: Connection, solver_name: str, n: int, seed: int, time_limit: float) -> None:
    """Runs in the spawned process: sends "ready" after the set-up, then one result dict."""
    try:
        solver = SOLVERS[solver_name]
        warm_up(solver)
        problem = make_problem(np.random.default_rng([seed, 2, n]), n, SCALE_OUTLIER_RATE, "uniform")
        _reset_peak_rss()
        before = _peak_rss_mb()
        conn.send("ready")
        times: list[float] = []
        while not times or (len(times) < REPEATS and times[0] * REPEATS <= time_limit):
            start = time.perf_counter()
            T = solver(problem.source, problem.target, problem.noise_bound)
            times.append(time.perf_counter() - start)
        peak = _peak_rss_mb()
        rot, trans = pose_errors(T, problem.T_target_source)
        conn.send({
            "status": "ok", "runs": len(times), "time_median_s": float(np.median(times)),
            "peak_memory_mb": peak - before, "rot_err_deg": rot, "trans_err_m": trans,
            "success_10deg_1m": int(rot <= 10.0 and trans <= 1.0),
        })  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - reported as the row's status
        conn.send({"status": f"error: {type(exc).__name__}: {exc}"})
    finally:
        conn.close()


def _receive(receiver: Connection, timeout: float, what: str) -> str | dict[str, object]:
    if not receiver.poll(timeout):
        return {"status": f"timeout: {what} > {timeout:.0f} s"}
    return receiver.recv()


def measure(solver_name: str, n: int, seed: int, time_limit: float) -> dict[str, object]:
    """Time [s] and peak memory [MB] of one solver on N correspondences, in a fresh process; the status
    says 'ok', or why there are no figures (error, crash, timeout)."""
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_worker, args=(sender, solver_name, n, seed, time_limit), daemon=True)
    process.start()
    sender.close()
    try:
        ready = _receive(receiver, SETUP_TIMEOUT, "set-up")
        result = _receive(receiver, time_limit + 5.0, "solver call") if ready == "ready" else ready
    except EOFError:
        process.join(timeout=10)
        result = {"status": f"crashed (exit code {process.exitcode})"}
    process.join(timeout=10)
    if process.is_alive():
        process.kill()
        process.join()
    return cast(dict[str, object], result)


def _extrapolate(measured: list[tuple[int, float]], n: int) -> float:
    """Value at n on the power law through the last two (n, value) points, exponent at least 1
    (linear from a single point; 0 without any)."""
    if not measured:
        return 0.0
    n1, v1 = measured[-1]
    exponent = 1.0
    if len(measured) > 1 and measured[-2][1] > 0.0 and v1 > 0.0:
        n0, v0 = measured[-2]
        exponent = max(1.0, math.log(v1 / v0) / math.log(n1 / n0))
    return v1 * (n / n1) ** exponent


def scale_rows(solver_names: list[str], sizes: list[int], seed: int, time_limit: float) -> list[dict[str, object]]:
    """One row per solver and size, sizes ascending. A size is skipped (and marked so) when the solver's
    time, extrapolated from its smaller sizes, exceeds `time_limit` [s], when its extrapolated peak
    memory exceeds half the machine's memory, or after a timeout at a smaller size."""
    memory_limit_mb = 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    rows = []
    progress = tqdm(total=len(solver_names) * len(sizes), desc="scale", unit="run", dynamic_ncols=True)
    for name in solver_names:
        times: list[tuple[int, float]] = []  # (n, median time [s]) of the measured sizes
        memory: list[tuple[int, float]] = []  # (n, peak memory [MB])
        skip = ""
        for n in sorted(sizes):
            progress.set_postfix_str(f"{name} N={n}")
            row: dict[str, object] = {"part": "scale", "solver": name, "n": n, "outlier_rate": SCALE_OUTLIER_RATE}
            if not skip and _extrapolate(times, n) > time_limit:
                skip = f"skipped: ~{_extrapolate(times, n):.0f} s predicted > {time_limit:g} s"
            if not skip and _extrapolate(memory, n) > memory_limit_mb:
                skip = f"skipped: ~{_extrapolate(memory, n) / 1024:.0f} GB predicted > half the memory"
            if skip:
                row["status"] = skip
            else:
                row.update(measure(name, n, seed, time_limit))
                if row["status"] == "ok":
                    times.append((n, float(str(row["time_median_s"]))))
                    memory.append((n, float(str(row["peak_memory_mb"]))))
                elif str(row["status"]).startswith("timeout"):
                    skip = f"skipped: timed out at N={n}"
            rows.append(row)
            progress.update()
    progress.close()
    return rows
