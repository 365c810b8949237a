"""Simulated frames cached on disk: ray cast once, then read through memory maps (bounded memory for any length).

A cache folder holds points.f32 ((N, 3) float32, every frame's points one after another), times.f32 ((N,) float32
[s] per point, relative to the frame stamp; empty for frames without per-point time), offsets.npy ((F + 1,) int64,
frame k's points are rows offsets[k]:offsets[k + 1]) and stamps.npy ((F,) float64 [s]).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from pipelines.io.atomic import atomic_dir
from sandro_slam.scan import Scan


class CachedFrames:
    """The frames of a cache folder, as `Scan`s of float64 arrays, in order."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._offsets = np.load(folder / "offsets.npy")
        self._stamps = np.load(folder / "stamps.npy")
        total = int(self._offsets[-1])
        self._points = np.memmap(folder / "points.f32", dtype=np.float32, mode="r", shape=(total, 3))
        times_size = (folder / "times.f32").stat().st_size // 4
        self._times = np.memmap(folder / "times.f32", dtype=np.float32, mode="r") if times_size else None

    def __len__(self) -> int:
        return len(self._stamps)

    def __iter__(self) -> Iterator[Scan]:
        for k in range(len(self._stamps)):
            rows = slice(self._offsets[k], self._offsets[k + 1])
            times = np.empty(0) if self._times is None else self._times[rows].astype(np.float64)
            yield Scan(float(self._stamps[k]), self._points[rows].astype(np.float64), times)


def write_frame_cache(folder: Path, frames: Iterable[Scan]) -> CachedFrames:
    """Write `frames` (all with per-point times, or all without) into a new cache folder, atomically."""
    with atomic_dir(folder) as building:
        building.mkdir(parents=True)
        offsets, stamps, timed = [0], [], set()
        with open(building / "points.f32", "wb") as points, open(building / "times.f32", "wb") as times:
            for scan in frames:
                timed.add(len(scan.times) > 0)
                if len(timed) > 1 or len(scan.times) not in (0, len(scan.points)):
                    raise ValueError(f"frame {len(stamps)}: frames must all have one time per point, or none")
                np.ascontiguousarray(scan.points, dtype=np.float32).tofile(points)
                np.ascontiguousarray(scan.times, dtype=np.float32).tofile(times)
                offsets.append(offsets[-1] + len(scan.points))
                stamps.append(scan.timestamp)
        np.save(building / "offsets.npy", np.array(offsets, dtype=np.int64))
        np.save(building / "stamps.npy", np.array(stamps, dtype=np.float64))
    return CachedFrames(folder)
