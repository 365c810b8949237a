"""A simulated drive written as a ROS bag of sensor_msgs/PointCloud2 with its ground truth beside it (what
`sandro-simulate` writes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.io.atomic import atomic_path
from pipelines.io.bags import write_bag
from pipelines.io.trajectory import write_tum
from pipelines.simulation.sequence import simulate_sequence
from sandro_slam.scan import Scan

GROUND_TRUTH_RATE = 100.0  # [Hz]
DEFAULT_START_TIME = 1_700_000_000.0  # [s] header.stamp of the first sweep (2023-11-14, a plausible ROS time)


def ground_truth_path(out: str | Path) -> Path:
    """Where `sandro-simulate OUT` writes the ground truth: OUT.gt.tum beside OUT."""
    out = Path(out)
    return out.with_name(out.name + ".gt.tum")


def simulate_bag(
    out: Path,
    fmt: str,
    seed: int = 0,
    laps: int = 2,
    frames: int | None = None,
    noise: float = 0.02,
    topic: str = "/points",
    start_time: float = DEFAULT_START_TIME,
    overwrite: bool = False,
    progress: bool = False,
) -> int:
    """Simulate a drive into the bag `out` and its ground truth into `ground_truth_path(out)`; returns the
    number of scans. Both appear together at the end (each written atomically), or neither on an error."""
    sequence = simulate_sequence(seed=seed, laps=laps, frames=frames, noise_sigma=noise)
    period = sequence.lidar.sweep_period
    gt_times = np.arange(round(len(sequence) * period * GROUND_TRUTH_RATE) + 1) / GROUND_TRUTH_RATE
    scans = sequence.frames()
    if progress:
        from tqdm import tqdm

        scans = tqdm(scans, total=len(sequence), unit="scan", desc="sandro-simulate", dynamic_ncols=True)
    with atomic_path(ground_truth_path(out)) as gt_tmp:
        write_tum(gt_tmp, start_time + gt_times, sequence.poses_at(gt_times))
        return write_bag(
            out,
            fmt,
            (Scan(start_time + f.timestamp, f.points, f.times) for f in scans),
            topic=topic,
            overwrite=overwrite,
        )
