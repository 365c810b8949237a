"""KISS-SLAM (pip package kiss-slam) run over the same frames, as its own pipeline does, for comparison."""

from __future__ import annotations

import ctypes
import os
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import numpy as np


def kiss_slam_available() -> bool:
    """Whether the optional package kiss-slam imports."""
    try:
        import kiss_slam  # noqa: F401
    except ImportError:
        return False
    return True


def run_kiss_slam(frames: Iterable, max_range: float) -> tuple[np.ndarray, float]:
    """(poses (N, 4, 4) T_world_sensor per frame, seconds) of KISS-SLAM with its default configuration.

    Frames are (timestamp, points, per-point times) as `OfflineSlam` takes them. Poses refer to the same
    time as KISS-ICP's (the latest point of each sweep). The steps are those of KISS-SLAM's own pipeline:
    process every scan, close the last local map, then its fine-grained optimisation.
    """
    from kiss_slam.config import KissSLAMConfig
    from kiss_slam.slam import KissSLAM

    config = KissSLAMConfig()
    config.odometry.preprocessing.max_range = max_range
    config.odometry.mapping.voxel_size = max_range / 100.0  # what KISS-SLAM's own config loader sets
    slam = KissSLAM(config)
    start = time.perf_counter()
    with _native_output_silenced():  # its g2o back end prints every iteration
        for _, points, times in frames:
            slam.process_scan(points, times)
        slam.generate_new_node()
        slam.local_map_graph.erase_last_local_map()
        poses, _ = slam.fine_grained_optimization()
    return np.asarray(poses), time.perf_counter() - start


@contextmanager
def _native_output_silenced() -> Iterator[None]:
    """Send what native code writes to stdout and stderr to /dev/null."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            ctypes.CDLL(None).fflush(None)  # what the C++ side buffered goes to /dev/null too
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)
