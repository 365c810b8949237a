"""Point cloud files: PLY written with the precision asked for and 8-bit colours, read back; submaps merged."""

import numpy as np
import open3d as o3d
import pytest

from pipelines.io.pointclouds import load_point_cloud, submaps_cloud, write_point_cloud


def _header(path) -> str:
    return path.read_bytes().split(b"end_header")[0].decode()


def test_write_point_cloud_precision_and_colours(tmp_path):
    points = np.random.default_rng(0).uniform(-50.0, 50.0, size=(100, 3))
    assert write_point_cloud(tmp_path / "d.ply", points) == 100
    assert "property double x" in _header(tmp_path / "d.ply")
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "d.ply"), points)

    colors = np.tile([[1.0, 0.5, 0.0]], (100, 1))
    write_point_cloud(tmp_path / "f.ply", points, colors, dtype=np.float32)
    assert "property float x" in _header(tmp_path / "f.ply") and "property uchar red" in _header(tmp_path / "f.ply")
    cloud = o3d.io.read_point_cloud(str(tmp_path / "f.ply"))
    np.testing.assert_allclose(np.asarray(cloud.points), points, atol=1e-5)
    np.testing.assert_allclose(np.asarray(cloud.colors)[0], [1.0, 128 / 255, 0.0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.ply", "f.ply"]  # no temporary file left


def test_submaps_cloud_moves_and_voxelises():
    submap = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [1.0, 0.0, 0.0]])
    T = np.eye(4)
    T[:3, 3] = [10.0, 0.0, 0.0]
    points = submaps_cloud([(submap, np.eye(4)), (submap, T)], voxel=0.5)
    assert len(points) == 4 and points[:, 0].max() > 10.5


def test_unknown_and_empty_files(tmp_path):
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="unknown point cloud format"):
        load_point_cloud(tmp_path / "a.xyz")
    (tmp_path / "e.bin").write_bytes(b"")
    with pytest.raises(ValueError, match="do not form records"):
        load_point_cloud(tmp_path / "e.bin")
