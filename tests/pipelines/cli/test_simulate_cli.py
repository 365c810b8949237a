"""`sandro-simulate`: a bag and its ground truth, refusals to overwrite, bad arguments in one line."""

import numpy as np
import pytest

from pipelines.cli.simulate import main
from pipelines.io.bags import BagScans, read_pose_topic
from pipelines.io.trajectory import read_tum
from pipelines.simulation import simulate_sequence
from pipelines.simulation.export import ground_truth_path


def test_simulate_cli(tmp_path, capsys):
    out = tmp_path / "sim.bag"
    assert main([str(out), "--frames", "3", "--seed", "2", "--noise", "0.01"]) == 0
    assert "wrote" in capsys.readouterr().out
    with BagScans(out) as bag:
        stamps = [stamp for stamp, _, _ in bag]
    gt_times, gt_poses = read_tum(ground_truth_path(out))
    assert ground_truth_path(out).name == "sim.bag.gt.tum"
    assert np.allclose(np.diff(gt_times), 0.01, atol=1e-6) and gt_times[0] == pytest.approx(stamps[0], abs=1e-6)
    assert gt_times[-1] == pytest.approx(stamps[-1] + 0.1, abs=1e-6)
    sequence = simulate_sequence(seed=2, frames=3)
    np.testing.assert_allclose(gt_poses[::10][:3], sequence.ground_truth, atol=1e-6)

    assert main([str(out), "--frames", "3"]) == 2  # refuses to overwrite
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists (use --force" in err
    assert main([str(tmp_path / "folder"), "--frames", "2", "--format", "ros2-sqlite3"]) == 0
    assert main([str(tmp_path / "folder"), "--frames", "1", "--format", "ros2-mcap", "--force"]) == 0
    assert BagScans(tmp_path / "folder").count == 1
    livox = [str(tmp_path / "livox.bag"), "--frames", "2", "--seed", "2", "--noise", "0.01", "--message", "livox"]
    assert main(livox) == 0
    with BagScans(tmp_path / "livox.bag") as bag, BagScans(out) as reference:
        assert bag._reader.topics["/points"].msgtype == "livox_ros_driver/msg/CustomMsg"
        for (stamp, points, times), (stamp0, points0, times0) in zip(bag, reference):  # the same scans
            assert stamp == stamp0 and np.array_equal(points, points0) and np.array_equal(times, times0)
    capsys.readouterr()
    bad_arguments = [
        [],
        ["x.bag", "--laps", "0"],
        ["x.bag", "--format", "ros3"],
        ["y", "--format", "ros1"],
        ["x.bag", "--noise", "-1"],
        ["x.bag", "--frames", "two"],
        ["x.bag", "--message", "xyz"],
        ["y", "--format", "kitti", "--message", "livox"],
        ["y", "--format", "keyframes", "--odometry-topic", "/odometry"],
        ["x.bag", "--odometry-topic", "odometry.tum"],
    ]
    for arguments in bad_arguments:
        assert main([str(tmp_path / arguments[0]), *arguments[1:]] if arguments else []) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("sandro-simulate: error:"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "folder", "folder.gt.tum", "livox.bag", "livox.bag.gt.tum", "sim.bag", "sim.bag.gt.tum"
    ]  # fmt: skip


@pytest.mark.parametrize(("fmt", "files"), [("folder", "000002.pcd"), ("kitti", "velodyne/000002.bin"),
                                            ("keyframes", "000002.pcd")])  # fmt: skip
def test_simulate_scan_folders(tmp_path, capsys, fmt, files):
    out = tmp_path / fmt
    assert main([str(out), "--format", fmt, "--frames", "3"]) == 0
    assert (out / files).is_file() and len(np.loadtxt(out / "times.txt")) == 3
    assert ground_truth_path(out).is_file()
    assert (out / "poses.txt").is_file() == (fmt != "folder")
    assert main([str(out), "--format", fmt, "--frames", "3"]) == 2  # refuses to overwrite
    assert "exists (use --force" in capsys.readouterr().err


def test_simulate_a_front_ends_bag(tmp_path, capsys):
    out = tmp_path / "lio.bag"
    assert main([str(out), "--frames", "4", "--odometry-topic", "/Odometry", "--drift", "0"]) == 0
    assert "deskewed, odometry on /Odometry" in capsys.readouterr().out
    times, poses = read_pose_topic(out, "/Odometry")
    with BagScans(out) as bag:
        scans = list(bag)
    assert [stamp for stamp, _, _ in scans] == pytest.approx(times, abs=1e-6)  # a pose at each scan's stamp
    assert all(len(scan_times) == 0 for _, _, scan_times in scans)  # deskewed: no per-point time
    gt_times, gt_poses = read_tum(ground_truth_path(out))
    at = np.searchsorted(gt_times, times - 1e-6)
    np.testing.assert_allclose(poses[:, :3, 3], gt_poses[at, :3, 3], atol=2e-3)  # no drift: the truth
