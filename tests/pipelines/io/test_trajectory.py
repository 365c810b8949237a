"""Pose files: TUM, KITTI, format detection, atomic writes, 4x4 transforms and keyframe pose lists."""

import numpy as np
import pytest

from pipelines.io.trajectory import (
    read_keyframe_poses,
    read_trajectory,
    read_transform,
    read_tum,
    write_kitti,
    write_tum,
)


def test_tum_round_trip(tmp_path, walk):
    poses, stamps = walk(), np.arange(50) * 0.1 + 1e9
    write_tum(tmp_path / "t.tum", stamps, poses)
    read_stamps, read_poses = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(read_stamps, stamps)
    np.testing.assert_allclose(read_poses, poses, atol=1e-8)


def test_kitti_layout(tmp_path, walk):
    poses = walk(3)
    write_kitti(tmp_path / "k.txt", poses)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "k.txt").reshape(3, 3, 4), poses[:, :3, :], atol=1e-8)


def test_values_that_print_as_zero_have_no_sign(tmp_path):
    pose = np.eye(4)
    pose[:3, 3] = [-1e-12, 1e-12, -4e-10]
    write_tum(tmp_path / "t.tum", np.array([-1e-12]), pose[None])
    write_kitti(tmp_path / "k.txt", pose[None])
    for name in ("t.tum", "k.txt"):
        assert "-" not in (tmp_path / name).read_text()


def test_not_a_tum_file(tmp_path):
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="8 columns"):
        read_tum(tmp_path / "bad.txt")


def test_kitti_round_trip_and_format_detection(tmp_path, walk):
    poses, stamps = walk(5), np.arange(5) * 0.1
    write_kitti(tmp_path / "k.txt", poses)
    write_tum(tmp_path / "t.txt", stamps, poses)
    times, read = read_trajectory(tmp_path / "k.txt")
    assert times is None
    np.testing.assert_allclose(read, poses, atol=1e-8)
    times, read = read_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(times, stamps)
    np.testing.assert_allclose(read, poses, atol=1e-8)


@pytest.mark.parametrize("text", ["", "1 2 3\n", "a b c d e f g h\n"])
def test_a_file_that_is_no_trajectory(tmp_path, text):
    (tmp_path / "bad.txt").write_text(text)
    with pytest.raises(ValueError, match="bad.txt"):
        read_trajectory(tmp_path / "bad.txt")
    with pytest.raises(ValueError, match="no such"):
        read_trajectory(tmp_path / "missing.txt")


def test_writes_leave_no_partial_file(tmp_path):
    with pytest.raises(ValueError):
        write_tum(tmp_path / "t.tum", np.arange(3), np.zeros((3, 3, 3)))
    assert list(tmp_path.iterdir()) == []


def test_transform_and_keyframe_pose_files(tmp_path, walk):
    T = walk(2)[1]
    np.savetxt(tmp_path / "T.txt", T)
    np.testing.assert_allclose(read_transform(tmp_path / "T.txt"), T, atol=1e-12)
    np.savetxt(tmp_path / "bad.txt", np.eye(4)[:3])
    with pytest.raises(ValueError, match="4x4"):
        read_transform(tmp_path / "bad.txt")

    poses = walk(3)
    times = np.array([3.0, 5.0, 9.0])
    write_tum(tmp_path / "t.tum", times, poses)
    lines = (tmp_path / "t.tum").read_text().splitlines()
    keyframe_lines = [f"v{int(t)}" + line[line.index(" ") :] for t, line in zip(times, lines)]
    (tmp_path / "kf.txt").write_text("\n".join(keyframe_lines) + "\n")
    read = read_keyframe_poses(tmp_path / "kf.txt")
    assert list(read) == [3, 5, 9]
    np.testing.assert_allclose(np.stack(list(read.values())), poses, atol=1e-8)
    (tmp_path / "kf.txt").write_text("3 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="kf.txt:1"):
        read_keyframe_poses(tmp_path / "kf.txt")
