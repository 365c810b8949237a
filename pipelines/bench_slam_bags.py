"""The bag part of `sandro-bench slam`: the simulated drive written as a bag in each format and run end to end
through `sandro-slam`'s `run_bag`, and the reading speed of a 64-beam-sized bag."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipelines.bag_io import FORMATS, bag_path, delete_bag
from pipelines.bench_bags import bag_read_speed
from pipelines.simulate import ground_truth_path, simulate_bag
from pipelines.slam import run_bag
from pipelines.trajectory_io import read_trajectory
from sandro_slam import SlamConfig


def bag_experiment(out: Path, config: SlamConfig, seed: int, laps: int, frames: int | None,
                   formats: tuple[str, ...] = FORMATS, read_scans: int = 100) -> dict[str, float]:
    """Per format: write the drive as a bag (in out/bags, removed afterwards), run `run_bag` with the ground
    truth, and report its ATE before/after loop closure, frames/s and the share of the run spent reading the bag;
    then the reading speed of a 64 x 2048-point, 10 Hz bag of `read_scans` scans as a multiple of real time."""
    metrics: dict[str, float] = {}
    folder = out / "bags"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for fmt in formats:
            bag = bag_path(folder, "drive", fmt)
            print(f"bag {fmt}: simulating, then sandro-slam ...", flush=True)
            simulate_bag(bag, fmt, seed=seed, laps=laps, frames=frames, overwrite=True)
            _, run = run_bag(bag, out / f"sandro-slam_{fmt}", config,
                             ground_truth=read_trajectory(ground_truth_path(bag)), progress=True)
            metrics[f"bag_{fmt}_ate_kiss_icp"] = run["ground_truth"]["ate_odometry_m"]
            metrics[f"bag_{fmt}_ate_sandro_slam"] = run["ground_truth"]["ate_slam_m"]
            metrics[f"bag_{fmt}_fps"] = run["frames_per_s"]
            metrics[f"bag_{fmt}_read_share"] = run["bag_read_s"] / run["wall_s"]
            delete_bag(bag)  # ~350 MB each
            ground_truth_path(bag).unlink()
        for fmt in formats:
            print(f"bag {fmt}: reading speed of a 64-beam bag ...", flush=True)
            speed = bag_read_speed(folder, fmt, read_scans)
            metrics[f"bag_{fmt}_read_realtime_factor_64beam"] = speed["realtime_factor"]
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return metrics
