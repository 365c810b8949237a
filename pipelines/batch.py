"""Many inputs, one sandro-slam run each: in this process, or as Ray tasks on a local Ray or an existing cluster.

Each input writes its own results folder, OUT/<name>/<YYYYmmdd-HHMMSS> with OUT/<name>/latest pointing at it
(`slam_run.run_input`), where <name> is the input's file or folder name without suffix (made unique with -2, -3
where two inputs share one). The batch summary (`batch.csv`, `batch.json` in OUT) has one row per input: its status
(done; failed; skipped by --resume; stopped by Ctrl-C, what was read written; cancelled), frames, loops, frames/s,
ATE where a ground truth is given, peak memory and the one-line error of a failed input. A failed input never stops
the others.

Ray is an optional dependency (`pip install .[cluster]`): one worker runs in this process without it.
"""

from __future__ import annotations

import json
import resource
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from pipelines.cli.entry import one_line
from pipelines.cluster import ray_session, threads_limited
from pipelines.io.atomic import write_text_atomic
from pipelines.io.inputs import names_bag_poses
from sandro_slam import SlamConfig

SUMMARY_FIELDS = [
    "input", "name", "status", "results", "frames", "keyframes", "loops_accepted", "loops_rejected", "frames_per_s",
    "wall_s", "ate_odometry_m", "ate_slam_m", "peak_rss_mb", "error",
]  # fmt: skip


@dataclass(frozen=True)
class Job:
    """One input of a batch and everything its run needs (picklable: it travels to Ray workers)."""

    input: Path
    out: Path  # this input's results base: OUT/<name>
    config: SlamConfig
    fmt: str | None = None
    topic: str | None = None
    rate: float | None = None
    gt: str | None = None  # a trajectory file, or poses in the input bag: a topic, tf:FRAME (`io.inputs.read_poses`)
    odometry: str | None = None
    max_frames: int | None = None
    map_voxel: float = 0.2
    threads: int = 0  # threads the run may use; 0: all


def jobs_for(inputs: list[Path], out: Path, gt: str | None = None, odometry: str | None = None, **common) -> list[Job]:
    """A Job per input, its results under OUT/<name>; `gt` and `odometry` are trajectory files or, for several
    inputs, patterns where {name} stands for the input's name (the stem of a file, the name of a folder), or poses
    every input bag holds: a topic, tf:FRAME (`io.inputs.read_poses`).

    Raises:
        ValueError: several inputs and a `gt` or `odometry` that is neither a pattern nor poses in a bag.
    """
    for option, value in (("--gt", gt), ("--odometry", odometry)):
        if value is None or len(inputs) == 1 or "{name}" in value:
            continue
        if Path(value).is_file() or not names_bag_poses(value):
            raise ValueError(
                f"{option} {value}: with several inputs, a pattern with {{name}} (e.g. gt/{{name}}.tum) or a topic"
            )
    jobs, taken = [], set()
    for path in inputs:
        stem = path.name if path.is_dir() else path.stem
        name, k = stem, 1
        while name in taken:
            k += 1
            name = f"{stem}-{k}"
        taken.add(name)
        jobs.append(Job(
            path, out / name,
            gt=gt.replace("{name}", stem) if gt is not None else None,
            odometry=odometry.replace("{name}", stem) if odometry is not None else None,
            **common,
        ))  # fmt: skip
    return jobs


def run_job(job: Job, ctrl_c: bool = False) -> dict:
    """Run one input; returns its summary row. Every error of the input becomes status 'failed' with the error's
    one line. `ctrl_c`: the first Ctrl-C stops reading this input and still writes its results (`run_input`)."""
    from pipelines.io.inputs import read_poses
    from pipelines.slam_run import run_input

    try:
        notes: list[str] = []
        ground_truth, odometry = (
            read_poses(value, job.input, job.fmt, job.topic, notes) if value is not None else None
            for value in (job.gt, job.odometry)
        )
        for note in notes:
            print(f"sandro-slam: {job.input}: {note}", file=sys.stderr, flush=True)
        with _threads_limited(job.config, job.threads) as config:
            folder, metrics = run_input(
                job.input, job.out, config, fmt=job.fmt, topic=job.topic, rate=job.rate, ground_truth=ground_truth,
                odometry=odometry, max_frames=job.max_frames, map_voxel=job.map_voxel, ctrl_c=ctrl_c,
            )  # fmt: skip
    except Exception as error:  # noqa: BLE001 - a corrupt input may fail anywhere; the batch goes on
        return {**_head(job, "failed"), "error": one_line(error)}
    status = "stopped" if metrics["interrupted"] else "done"
    return {**_head(job, status), **_row(folder, metrics), "peak_rss_mb": _peak_rss_mb()}


def finished_row(job: Job) -> dict | None:
    """The summary row of an input whose results are complete (OUT/<name>/latest, set when a run has written
    everything, holds the metrics of a run that read the whole input), with status 'skipped'; None otherwise."""
    path = job.out / "latest" / "metrics.json"
    if not path.is_file():
        return None
    metrics = json.loads(path.read_text())
    if metrics.get("interrupted"):
        return None
    return {**_head(job, "skipped"), **_row(path.parent.resolve(), metrics)}


def run_batch(
    jobs: list[Job],
    workers: int = 1,
    ray_address: str | None = None,
    resume: bool = False,
    progress: bool = True,
    on_row: Callable[[list[dict]], None] | None = None,
) -> list[dict]:
    """Run `jobs` and return their summary rows, in the order of `jobs`.

    workers 1 without `ray_address`: one after the other in this process (Ctrl-C: the current input stops reading
    and is written, the rest is cancelled). Otherwise Ray tasks of one CPU each: on a new local Ray with `workers`
    CPUs, or on the cluster at `ray_address` ('auto' as Ray defines it), where Ray places them (Ctrl-C cancels
    what runs and is pending). `resume`: inputs whose results are complete are skipped. `on_row` gets the rows
    so far after each input (to write the summary as the batch goes).

    Raises:
        ValueError: workers < 1, or Ray needed and not installed.
    """
    if workers < 1:
        raise ValueError(f"--workers {workers}: at least 1")
    rows: list[dict | None] = [finished_row(job) if resume else None for job in jobs]
    todo = [i for i, row in enumerate(rows) if row is None]
    bar = _progress(len(jobs), len(jobs) - len(todo), progress)
    try:
        if workers == 1 and ray_address is None:
            _serial(jobs, todo, rows, bar, on_row)
        else:
            _on_ray(jobs, todo, rows, bar, on_row, workers, ray_address)
    except KeyboardInterrupt:  # the summary still lists every input, the unfinished ones as cancelled
        if on_row:
            on_row(_every_row(rows, jobs))
        raise
    finally:
        bar.close()
    return _every_row(rows, jobs)


def write_summary(out: Path, rows: list[dict]) -> None:
    """batch.csv and batch.json in `out` (each written whole or not at all)."""
    import csv
    import io

    text = io.StringIO()
    writer = csv.DictWriter(text, SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "batch.csv", text.getvalue())
    write_text_atomic(out / "batch.json", json.dumps(rows, indent=2) + "\n")


def _serial(jobs: list[Job], todo: list[int], rows: list, bar, on_row) -> None:
    for i in todo:
        rows[i] = run_job(jobs[i], ctrl_c=True)
        bar.update()
        if on_row:
            on_row([r for r in rows if r is not None])
        if rows[i]["status"] == "stopped":  # Ctrl-C: what was read of this input is written, the rest cancelled
            return


def _on_ray(jobs: list[Job], todo: list[int], rows: list, bar, on_row, workers: int, address: str | None) -> None:
    threads = {job.threads for job in jobs}
    with ray_session(workers, address, threads.pop() if len(threads) == 1 else 0):
        import ray

        task = ray.remote(num_cpus=1, max_retries=0)(run_job)
        pending = {task.remote(jobs[i]): i for i in todo}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                i = pending.pop(done[0])
                try:
                    rows[i] = ray.get(done[0])
                except ray.exceptions.RayError as error:  # the worker died (out of memory, killed)
                    rows[i] = {**_head(jobs[i], "failed"), "error": one_line(error)[:500]}
                bar.update()
                if on_row:
                    on_row([r for r in rows if r is not None])
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise


@contextmanager
def _threads_limited(config: SlamConfig, threads: int) -> Iterator[SlamConfig]:
    """`config` with KISS-ICP limited to `threads`, and this process likewise (`cluster.threads_limited`) while
    the block runs; 0: unchanged. KISS-ICP sets its thread count once per process, at its first registration
    (a process-wide TBB limit): the runs of one process must ask for the same count."""
    if threads <= 0:
        yield config
        return
    odometry = config.odometry.model_copy(deep=True)
    odometry.registration.max_num_threads = threads
    with threads_limited(threads):
        yield config.model_copy(update={"odometry": odometry})


def _row(folder: Path, metrics: dict) -> dict:
    truth = metrics.get("ground_truth", {})
    return {
        "results": str(folder), "frames": metrics["frames"], "keyframes": metrics["keyframes"],
        "loops_accepted": metrics["loops_accepted"], "loops_rejected": metrics["loops_rejected"],
        "frames_per_s": round(metrics["frames_per_s"], 3), "wall_s": round(metrics["wall_s"], 3),
        "ate_odometry_m": truth.get("ate_odometry_m"), "ate_slam_m": truth.get("ate_slam_m"), "error": None,
    }  # fmt: skip


def _peak_rss_mb() -> float:
    """The peak resident memory [MB] of this process and, separately counted, of its largest finished child (the
    loop-closure worker): what running an input took at most, in a process that ran nothing larger before."""
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return round((self_kb + children_kb) / 1024.0, 1)


def _head(job: Job, status: str) -> dict:
    """The columns of a summary row that every input has."""
    return {"input": str(job.input), "name": job.out.name, "status": status}


def _every_row(rows: list[dict | None], jobs: list[Job]) -> list[dict]:
    """A row per job: those without one yet are cancelled."""
    return [row or _head(job, "cancelled") for row, job in zip(rows, jobs)]


class _NoBar:
    def update(self) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, done: int, show: bool):
    if not show:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=done, unit="input", desc="sandro-slam batch", file=sys.stderr)
