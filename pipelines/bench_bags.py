"""Bag reading speed: how much faster than real time `BagScans` reads and decodes a 64-beam-sized bag."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipelines.bag_io import BagScans, bag_path, delete_bag, write_bag

BEAMS, COLUMNS, RATE = 64, 2048, 10.0  # an Ouster OS-64 in 2048 x 10 mode


def _ouster_like_scans(count: int, seed: int) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
    """`count` synthetic scans of BEAMS x COLUMNS points at RATE: random ranges on a spinning fan of beams,
    5 % no-return points at the origin (as the Ouster driver publishes them), per-point times by column."""
    rng = np.random.default_rng(seed)
    azimuth = np.repeat(np.linspace(np.pi, -np.pi, COLUMNS, endpoint=False), BEAMS)
    elevation = np.tile(np.deg2rad(np.linspace(-22.5, 22.5, BEAMS)), COLUMNS)
    directions = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                           np.sin(elevation)], axis=1)
    times = np.repeat(np.arange(COLUMNS) / (COLUMNS * RATE), BEAMS)
    for index in range(count):
        ranges = rng.uniform(1.0, 80.0, BEAMS * COLUMNS)
        ranges[rng.random(BEAMS * COLUMNS) < 0.05] = 0.0
        yield 1_700_000_000.0 + index / RATE, ranges[:, None] * directions, times


def bag_read_speed(folder: Path, fmt: str, scans: int = 100, seed: int = 0) -> dict:
    """Write a bag of `scans` Ouster-like scans (64 x 2048 points, ouster-ros layout: point_step 48, t in ns)
    in format `fmt` into `folder`, time opening it and iterating `BagScans` over it (read + decode, the bag
    being in the page cache just after writing), then remove the bag (~6.3 MB per scan).

    Returns {"format", "scans", "points_per_scan", "read_s", "realtime_factor"}: the factor is the bag's
    duration at 10 Hz over read_s.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = bag_path(folder, "bag_read_speed", fmt)
    write_bag(path, fmt, _ouster_like_scans(scans, seed), layout="ouster", overwrite=True)
    try:
        start = time.perf_counter()
        points = 0
        with BagScans(path) as bag:
            for _, xyz, _ in bag:
                points += len(xyz)
        read_s = time.perf_counter() - start
    finally:
        delete_bag(path)
    return {"format": fmt, "scans": scans, "points_per_scan": BEAMS * COLUMNS, "read_s": read_s,
            "realtime_factor": scans / RATE / read_s, "points_read_per_scan": points / max(scans, 1)}
