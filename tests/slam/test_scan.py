"""Scans as OfflineSlam takes them: Scans, tuples with or without per-point times."""

import numpy as np
import pytest

from sandro_slam.scan import Scan, as_scan, occupied_voxels


def test_tuples_and_scans_become_float64_scans():
    points = np.arange(12, dtype=np.float32).reshape(4, 3)
    for frame in ((1, points), (1, points, None), (1, points, np.empty(0)), Scan(1.0, points, np.empty(0))):
        scan = as_scan(frame, 0)
        assert isinstance(scan, Scan) and scan.timestamp == 1.0 and len(scan.times) == 0
        assert scan.points.dtype == np.float64 and np.array_equal(scan.points, points)
    scan = as_scan((2.5, points, np.arange(4, dtype=np.uint32)), 0)
    assert scan.times.dtype == np.float64 and scan.times.tolist() == [0.0, 1.0, 2.0, 3.0]
    assert len(as_scan((2.5, points, np.full(4, 0.03)), 0).times) == 0  # one firing's time for all: no time


def test_occupied_voxels_counts_the_voxels_within_range():
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.3, 0.1], [1.5, 0.2, 0.0], [5.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    assert occupied_voxels(points, 1.0, 0.0, 100.0) == 4
    assert occupied_voxels(points, 1.0, 1.0, 10.0) == 2
    assert occupied_voxels(points, 1.0, 60.0, 100.0) == 0


def test_bad_frames_name_their_index():
    with pytest.raises(ValueError, match="frame 3: expected"):
        as_scan((1.0,), 3)
    with pytest.raises(ValueError, match=r"frame 4: points must be an \(N, 3\) array"):
        as_scan((1.0, np.zeros(3)), 4)
    with pytest.raises(ValueError, match="frame 5: 2 per-point times for 3 points"):
        as_scan((1.0, np.zeros((3, 3)), np.zeros(2)), 5)
