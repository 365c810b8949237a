"""The bag part of `sandro-bench slam`: the simulated drive written as a bag in each format (and as a ROS1 bag of
Livox CustomMsg) and run end to end through `sandro-slam`'s `run_input`, and how much faster than real time
`BagScans` reads a 64-beam-sized bag."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipelines.io.bags import FORMATS, BagScans, bag_path, delete_bag, read_pose_topic, write_bag
from pipelines.io.trajectory import read_trajectory
from pipelines.simulation.export import ground_truth_path, simulate
from pipelines.slam_run import run_input
from sandro_slam import Scan, SlamConfig

BEAMS, COLUMNS, RATE = 64, 2048, 10.0  # an Ouster OS-64 in 2048 x 10 mode


def _ouster_like_scans(count: int, seed: int) -> Iterator[Scan]:
    """`count` synthetic scans of BEAMS x COLUMNS points at RATE: random ranges on a spinning fan of beams,
    5 % no-return points at the origin (as the Ouster driver publishes them), per-point times by column."""
    rng = np.random.default_rng(seed)
    azimuth = np.repeat(np.linspace(np.pi, -np.pi, COLUMNS, endpoint=False), BEAMS)
    elevation = np.tile(np.deg2rad(np.linspace(-22.5, 22.5, BEAMS)), COLUMNS)
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    times = np.repeat(np.arange(COLUMNS) / (COLUMNS * RATE), BEAMS)
    for index in range(count):
        ranges = rng.uniform(1.0, 80.0, BEAMS * COLUMNS)
        ranges[rng.random(BEAMS * COLUMNS) < 0.05] = 0.0
        yield Scan(1_700_000_000.0 + index / RATE, ranges[:, None] * directions, times)


def bag_read_speed(folder: Path, fmt: str, scans: int = 100, seed: int = 0, message: str = "pointcloud2") -> dict:
    """Write a bag of `scans` Ouster-like scans (64 x 2048 points; as PointCloud2 in the ouster-ros layout:
    point_step 48, t in ns; or as Livox CustomMsg, `message` "livox") in format `fmt` into `folder`, time opening
    it and iterating `BagScans` over it (read + decode, the bag being in the page cache just after writing), then
    remove the bag (~6.3 MB per scan as PointCloud2, 2.5 MB as CustomMsg).

    Returns {"format", "message", "scans", "points_per_scan", "read_s", "realtime_factor"}: the factor is the
    bag's duration at 10 Hz over read_s.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = bag_path(folder, "bag_read_speed", fmt)
    write_bag(path, fmt, _ouster_like_scans(scans, seed), layout="ouster", overwrite=True, message=message)
    try:
        start = time.perf_counter()
        points = 0
        with BagScans(path) as bag:
            for _, xyz, _ in bag:
                points += len(xyz)
        read_s = time.perf_counter() - start
    finally:
        delete_bag(path)
    return {
        "format": fmt,
        "message": message,
        "scans": scans,
        "points_per_scan": BEAMS * COLUMNS,
        "read_s": read_s,
        "realtime_factor": scans / RATE / read_s,
        "points_read_per_scan": points / max(scans, 1),
    }


def bag_experiment(
    out: Path,
    config: SlamConfig,
    seed: int,
    laps: int,
    frames: int | None,
    formats: tuple[str, ...] = FORMATS,
    read_scans: int = 100,
    livox: bool = True,
) -> dict[str, float]:
    """Per format (and, with `livox`, a ROS1 bag of Livox CustomMsg, named "ros1_livox"; and a ROS2 mcap bag of
    what a LiDAR-inertial front end records, "ros2_lio": deskewed scans and its odometry, drifting by 0.5 %, as
    nav_msgs/Odometry): write the drive as a bag (in out/bags, removed afterwards), run `run_input` with the ground
    truth (on the bag's odometry topic for ros2_lio), and report its ATE before/after loop closure, frames/s and the
    share of the run spent reading the bag; then the reading speed of a 64 x 2048-point, 10 Hz bag of `read_scans`
    scans as a multiple of real time."""
    variants = [(fmt, "pointcloud2", fmt, None) for fmt in formats] + [("ros1", "livox", "ros1_livox", None)] * livox
    variants.append(("ros2-mcap", "pointcloud2", "ros2_lio", "/odometry"))
    metrics: dict[str, float] = {}
    folder = out / "bags"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for fmt, message, name, odometry_topic in variants:
            bag = bag_path(folder, "drive", fmt)
            print(f"bag {name}: simulating, then sandro-slam ...", flush=True)
            simulate(bag, fmt, seed=seed, laps=laps, frames=frames, overwrite=True, message=message,
                     odometry_topic=odometry_topic)  # fmt: skip
            _, run = run_input(
                bag,
                out / f"sandro-slam_{name}",
                config,
                ground_truth=read_trajectory(ground_truth_path(bag)),
                odometry=read_pose_topic(bag, odometry_topic) if odometry_topic else None,
                progress=True,
            )
            odometry = "given" if odometry_topic else "kiss_icp"
            metrics[f"bag_{name}_ate_{odometry}"] = run["ground_truth"]["ate_odometry_m"]
            metrics[f"bag_{name}_ate_sandro_slam"] = run["ground_truth"]["ate_slam_m"]
            metrics[f"bag_{name}_fps"] = run["frames_per_s"]
            metrics[f"bag_{name}_read_share"] = run["read_s"] / run["wall_s"]
            delete_bag(bag)  # ~350 MB each
            ground_truth_path(bag).unlink()
        for fmt, message, name, odometry_topic in variants:
            if odometry_topic:
                continue  # the same reader as the other ros2-mcap bag
            print(f"bag {name}: reading speed of a 64-beam bag ...", flush=True)
            speed = bag_read_speed(folder, fmt, read_scans, message=message)
            metrics[f"bag_{name}_read_realtime_factor_64beam"] = speed["realtime_factor"]
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return metrics
