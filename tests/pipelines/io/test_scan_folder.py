"""Scan folders: files in name order, scan times from times.txt, names or a rate, per-point times from PCD fields,
the KITTI layout and its ground truth, keyframe dumps; bad folders in one line."""

import numpy as np
import pytest

from pipelines.io.inputs import detect_format, open_input
from pipelines.io.pointclouds import write_kitti_bin, write_point_cloud
from pipelines.io.scan_folder import ScanFolder, stamps_from_names
from pipelines.io.trajectory import write_kitti

POINTS = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [0.0, 0.0, 0.0], [7.0, 8.0, 9.0]])  # one no-return point


def _pcd_folder(folder, count=3, times=True):
    folder.mkdir()
    for index in range(count):
        fields = {"t": np.array([0, 1000, 2000, 3000], dtype=np.uint32)} if times else None  # [ns]
        write_point_cloud(folder / f"{index:06d}.pcd", POINTS + index, dtype=np.float32, fields=fields)
    return folder


def test_pcd_scans_with_times_txt_and_a_time_field(tmp_path):
    folder = _pcd_folder(tmp_path / "scans")
    np.savetxt(folder / "times.txt", [10.0, 10.1, 10.2])
    scans = list(ScanFolder(folder))
    assert [scan.timestamp for scan in scans] == [10.0, 10.1, 10.2]
    np.testing.assert_allclose(scans[0].points, POINTS[[0, 1, 3]], atol=1e-6)  # the point at the origin dropped
    np.testing.assert_allclose(scans[0].times, [0.0, 1e-6, 3e-6])


@pytest.mark.parametrize("line", [True, False])
def test_livox_noise_tags_drop_points_only_beside_a_line_field(tmp_path, line):
    folder = tmp_path / "scans"
    folder.mkdir()
    fields = {"tag": np.array([0x00, 0x01, 0x10, 0x04], dtype=np.uint8)}  # kept, noise, 2nd return (kept), noise
    if line:
        fields["line"] = np.zeros(4, dtype=np.uint8)
    points = POINTS + 1.0  # no point at the origin
    write_point_cloud(folder / "000000.pcd", points, dtype=np.float32, fields=fields)
    scan = next(iter(ScanFolder(folder, rate=10.0)))
    np.testing.assert_allclose(scan.points, points[[0, 2]] if line else points, atol=1e-6)


def test_times_from_file_names_or_a_rate(tmp_path):
    assert stamps_from_names(["1700000000.5", "1700000000.6"]).tolist() == [1700000000.5, 1700000000.6]
    np.testing.assert_allclose(stamps_from_names(["1700000000000000000", "1700000000100000000"]), [1.7e9, 1.7e9 + 0.1])
    assert stamps_from_names(["000000", "000001"]) is None  # indices, not times
    assert stamps_from_names(["1700000000.6", "1700000000.5"]) is None  # not increasing
    folder = _pcd_folder(tmp_path / "scans", times=False)
    with pytest.raises(ValueError, match="no scan times"):
        ScanFolder(folder)
    assert ScanFolder(folder, rate=10.0).stamps.tolist() == [0.0, 0.1, 0.2]
    assert len(next(iter(ScanFolder(folder, rate=10.0))).times) == 0


def test_kitti_sequence_and_its_ground_truth_in_the_lidar_frame(tmp_path):
    sequence = tmp_path / "07"
    (sequence / "velodyne").mkdir(parents=True)
    for index in range(3):
        write_kitti_bin(sequence / "velodyne" / f"{index:06d}.bin", POINTS[[0, 1, 3]])
    np.savetxt(sequence / "times.txt", [0.0, 0.1, 0.2])
    T_cam_velo = np.eye(4)
    T_cam_velo[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]  # velodyne x forward -> camera z
    T_cam_velo[:3, 3] = [0.1, -0.2, -0.3]
    (sequence / "calib.txt").write_text(
        "P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(map(str, T_cam_velo[:3].ravel()))
    )
    velo = np.tile(np.eye(4), (3, 1, 1))
    velo[:, 0, 3] = [0.0, 1.0, 2.0]  # driving forward along the LiDAR's x
    write_kitti(sequence / "poses.txt", T_cam_velo @ velo @ np.linalg.inv(T_cam_velo))  # the camera's poses
    assert detect_format(sequence) == "kitti"
    with open_input(sequence) as source:
        times, poses = source.ground_truth
        assert times.tolist() == [0.0, 0.1, 0.2] and source.description["format"] == "kitti"
        np.testing.assert_allclose(poses, velo, atol=1e-9)
        assert len(list(source.scans)) == 3


def test_a_keyframe_dump_brings_its_odometry(tmp_path):
    folder = _pcd_folder(tmp_path / "dump", times=False)
    np.savetxt(folder / "times.txt", [0.0, 1.0, 2.0])
    write_kitti(folder / "poses.txt", np.tile(np.eye(4), (3, 1, 1)))
    assert detect_format(folder) == "keyframes"
    with open_input(folder) as source:
        times, poses = source.odometry
        assert times is None and poses.shape == (3, 4, 4)
    with open_input(folder, "folder") as source:  # named: its poses are ignored
        assert source.odometry is None


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda f: None, "no scan files"),
        (lambda f: [(f / "a.pcd").write_bytes(b"x"), (f / "b.bin").write_bytes(b"")], "several formats"),
        (lambda f: [(f / "0.pcd").write_text("not a point cloud"), (f / "times.txt").write_text("1\n")], "no points"),
        (lambda f: [(f / "0.bin").write_bytes(b"\0" * 12), (f / "times.txt").write_text("1\n2\n")], "2 times for 1"),
    ],
)
def test_bad_folders_say_what_is_wrong(tmp_path, make, message):
    folder = tmp_path / "scans"
    folder.mkdir()
    make(folder)
    with pytest.raises(ValueError, match=message) as error:
        list(ScanFolder(folder))
    assert "\n" not in str(error.value)
