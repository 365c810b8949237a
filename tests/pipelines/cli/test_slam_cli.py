"""`sandro-slam`: a bag in, a results folder out; bad input gets one line and a non-zero exit."""

import json
from pathlib import Path

import numpy as np
import pytest

from pipelines.cli.slam import main
from pipelines.io.bags import BagScans, write_bag
from pipelines.io.inputs import read_poses
from pipelines.io.trajectory import read_tum, write_kitti
from pipelines.simulation import simulate_sequence
from pipelines.simulation.export import ground_truth_path, simulate
from sandro_core.geometry import transform_points
from sandro_slam import Scan

FRAMES = 40
OUTPUTS = [
    "poses.tum",
    "poses.kitti",
    "odometry.tum",
    "odometry.kitti",
    "graph.g2o",
    "loops.csv",
    "map.ply",
    "trajectory.png",
    "config.yaml",
    "metrics.json",
]


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bags") / "city.bag"
    simulate(path, "ros1", frames=FRAMES)
    return path


def _one_line_error(capsys, *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("sandro-slam: error:"), err
    for word in words:
        assert word in err, err


@pytest.mark.slow
def test_a_run_writes_every_output_and_evaluates_against_the_ground_truth(bag, tmp_path, capsys):
    out = tmp_path / "results"
    assert main([str(bag), "--gt", str(ground_truth_path(bag)), "--out", str(out), "--quiet"]) == 0
    folder = (out / "latest").resolve()
    assert sorted(p.name for p in folder.iterdir() if p.is_file()) == sorted(OUTPUTS)
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["frames"] == FRAMES and metrics["topic"] == "/points" and not metrics["interrupted"]
    assert metrics["ground_truth"]["frames_matched"] == FRAMES
    assert metrics["ground_truth"]["ate_slam_m"] < 0.3
    times, poses = read_tum(folder / "poses.tum")
    assert len(times) == FRAMES and np.all(np.diff(times) > 0)
    assert times[0] > 1e9  # header stamps, on the bag's clock
    printed = capsys.readouterr().out
    assert "ATE odometry" in printed and str(folder.name) in printed
    assert "refine: false" in (folder / "config.yaml").read_text()  # auto: a car's steady drive, no second pass

    assert main([str(bag), "--out", str(out), "--quiet", "--max-frames", "5"]) == 0
    second = (out / "latest").resolve()
    assert second != folder and (folder / "metrics.json").is_file()  # a new folder; the old one is kept
    assert json.loads((second / "metrics.json").read_text())["frames"] == 5


@pytest.mark.parametrize("fmt", ["ros2-sqlite3", "ros2-mcap"])
def test_ros2_bags(tmp_path, fmt):
    path = tmp_path / "city"
    simulate(path, fmt, frames=8)
    assert main([str(path), "--gt", str(ground_truth_path(path)), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    assert json.loads((tmp_path / "r" / "latest" / "metrics.json").read_text())["frames"] == 8


def test_a_bag_without_per_point_times(tmp_path):
    # Deskewed clouds from a LiDAR-inertial front end carry no time field: read, and run without deskewing.
    scans = [
        (1_700_000_000.0 + 0.1 * i, scan.points, np.empty(0))
        for i, scan in enumerate(simulate_sequence(seed=3, frames=6).frames())
    ]
    write_bag(tmp_path / "no_times.bag", "ros1", scans)
    assert main([str(tmp_path / "no_times.bag"), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    metrics = json.loads((tmp_path / "r" / "latest" / "metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["frames_skipped"] == 0


def test_a_front_ends_bag_runs_on_its_odometry_topic(tmp_path, capsys):
    # What FAST-LIO2 records: deskewed scans and its odometry as nav_msgs/Odometry in one bag.
    bag = tmp_path / "lio"
    simulate(bag, "ros2-mcap", frames=60, odometry_topic="/odometry", drift=0.01)
    out = tmp_path / "r"
    assert main([str(bag), "--odometry", "/odometry", "--gt", str(ground_truth_path(bag)), "--out", str(out),
                 "--quiet"]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "also holds poses" not in err and "world frame" not in err, err
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    assert metrics["odometry"] == "given" and metrics["frames"] == 60 and metrics["frames_skipped"] == 0
    assert 0.01 < metrics["ground_truth"]["ate_odometry_m"] < 0.3  # the drift of the topic's poses, not KISS-ICP's
    odometry_times, odometry = read_tum(out / "latest" / "odometry.tum")
    topic_times, topic = read_poses("/odometry", bag)
    np.testing.assert_allclose(odometry_times, topic_times, atol=1e-6)
    np.testing.assert_allclose(odometry[:, :3, 3], topic[:, :3, 3], atol=1e-6)

    assert main([str(bag), "--max-frames", "3", "--out", str(out), "--quiet"]) == 0
    assert "the bag also holds poses: /odometry (nav_msgs/Odometry); --odometry TOPIC" in capsys.readouterr().err

    # The same scans in the odometry's world frame (FAST-LIO2's /cloud_registered): run, with a warning.
    world = tmp_path / "world.bag"
    with BagScans(bag) as scans:
        moved = [Scan(t, transform_points(T, points), times) for (t, points, times), T in zip(scans, topic)]
    write_bag(world, "ros1", moved, odometry=zip(topic_times, topic))
    assert main([str(world), "--odometry", "/odometry", "--out", str(out), "--quiet"]) == 0
    assert "warning: the scans seem to be in the odometry's world frame" in capsys.readouterr().err
    assert main([str(world), "--out", str(out), "--quiet"]) == 0  # KISS-ICP on them: it stands still
    assert "warning: the scans seem to be in a fixed world frame" in capsys.readouterr().err


def test_missing_and_corrupt_bags(tmp_path, capsys):
    assert main([str(tmp_path / "nope.bag"), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "nope.bag")
    corrupt = tmp_path / "corrupt.bag"
    corrupt.write_bytes(np.random.default_rng(0).bytes(5000))
    assert main([str(corrupt), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "corrupt.bag")
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").iterdir())


def test_wrong_topic_lists_the_choices(bag, tmp_path, capsys):
    assert main([str(bag), "--topic", "/velodyne", "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "/velodyne", "/points")


def test_empty_messages(tmp_path, capsys):
    path = tmp_path / "empty.bag"
    write_bag(path, "ros1", ((1.0 + 0.1 * i, np.empty((0, 3)), np.empty(0)) for i in range(3)))
    assert main([str(path), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    _one_line_error(capsys, "no frame")
    assert not any((tmp_path / "r").iterdir())  # no results folder left behind


def test_unwritable_out(bag, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main([str(bag), "--out", str(blocker / "r")]) == 2
    _one_line_error(capsys, "cannot write results")


@pytest.mark.parametrize(
    "text, words",
    [
        ("graph: [unclosed", ["not valid YAML"]),
        ("graph:\n  robust: magic\n", ["graph.robust"]),
        ("nonsense_key: 1\n", ["nonsense_key"]),
    ],
)
def test_malformed_config(bag, tmp_path, capsys, text, words):
    config = tmp_path / "c.yaml"
    config.write_text(text)
    assert main([str(bag), "--config", str(config), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "c.yaml", *words)


@pytest.mark.parametrize("text", ["1 2 3\n", "garbage\n"])
def test_malformed_ground_truth(bag, tmp_path, capsys, text):
    gt = tmp_path / "gt.txt"
    gt.write_text(text)
    assert main([str(bag), "--gt", str(gt), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "gt.txt")


@pytest.mark.slow
def test_ground_truth_from_another_time(bag, tmp_path, capsys):
    times, poses = read_tum(ground_truth_path(bag))
    gt = tmp_path / "late.tum"
    np.savetxt(gt, np.column_stack([times + 1e6, poses[:, :3, 3], np.tile([0, 0, 0, 1.0], (len(times), 1))]))
    assert main([str(bag), "--gt", str(gt), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    _one_line_error(capsys, "ground truth")
    assert not any((tmp_path / "r").iterdir())


@pytest.mark.slow
def test_ctrl_c_stops_and_still_writes_the_results(bag, tmp_path, interrupted_slam):
    out = tmp_path / "r"
    config = tmp_path / "config.yaml"
    config.write_text("scale: 1.0\n")  # scans are read one by one from the first: no head held to measure the scale

    def processing() -> bool:  # the run folder exists
        return out.is_dir() and any(out.iterdir())

    args = [str(bag), "--config", str(config), "--out", str(out), "--quiet"]
    returncode, stderr = interrupted_slam(args, processing, wait=60, settle=0.5)
    assert returncode == 0, stderr
    assert "Traceback" not in stderr and "stopping after this scan" in stderr
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    assert metrics["interrupted"] and 0 < metrics["frames"] < FRAMES
    assert (out / "latest" / "map.ply").is_file()


def test_the_same_scans_as_a_bag_and_as_a_folder_give_the_same_result(bag, tmp_path):
    folder = tmp_path / "city"
    simulate(folder, "folder", frames=FRAMES)  # PCD files: the bag's points and per-point times
    results = []
    for source in (bag, folder):
        assert main([str(source), "--out", str(tmp_path / source.name), "--quiet"]) == 0
        latest = tmp_path / source.name / "latest"
        results.append((read_tum(latest / "odometry.tum"), read_tum(latest / "poses.tum"), latest / "metrics.json"))
    (bag_times, bag_odometry), (bag_stamps, bag_poses), _ = results[0]
    (folder_times, folder_odometry), (_, folder_poses), metrics = results[1]
    np.testing.assert_allclose(folder_times, bag_times, atol=1e-6)
    np.testing.assert_allclose(folder_odometry, bag_odometry, atol=1e-6)
    np.testing.assert_allclose(folder_poses, bag_poses, atol=0.02)  # loop registrations use threads
    assert json.loads(metrics.read_text())["format"] == "folder"


def test_given_odometry_is_kept_where_no_loop_moves_it(tmp_path):
    # A KITTI sequence of deskewed scans; the odometry given: its true poses as TUM, matched by time.
    sequence = tmp_path / "kitti"
    simulate(sequence, "kitti", frames=FRAMES)
    truth = ground_truth_path(sequence)
    assert main([str(sequence), "--odometry", str(truth), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    latest = tmp_path / "r" / "latest"
    metrics = json.loads((latest / "metrics.json").read_text())
    assert metrics["odometry"] == "given" and metrics["loops_verified"] == 0
    assert metrics["ground_truth"]["ate_slam_m"] < 1e-4  # against its poses.txt, found beside it: exact poses
    times, poses = read_tum(latest / "poses.tum")
    gt_times, gt_poses = read_tum(truth)
    np.testing.assert_allclose(times, np.loadtxt(sequence / "times.txt"))
    np.testing.assert_allclose(poses[:, :3, 3], interpolated(gt_times, gt_poses, times)[:, :3, 3], atol=1e-6)


def interpolated(times, poses, at):
    from sandro_core.geometry import interpolate_poses

    mask, out = interpolate_poses(times, poses, at)
    assert mask.all()
    return out


@pytest.mark.parametrize(
    ("arguments", "words"),
    [
        (["--odometry", "{odometry}"], ["5 poses for", "scans"]),
        (["--format", "kitti"], ["not a KITTI sequence"]),
        (["--format", "tape"], ["unknown input format"]),
        (["--topic", "/points"], ["--topic is for bags"]),
    ],
)
def test_bad_scan_folder_inputs(tmp_path, capsys, arguments, words):
    folder = tmp_path / "scans"
    simulate(folder, "folder", frames=3)
    odometry = tmp_path / "odometry.kitti"
    write_kitti(odometry, np.tile(np.eye(4), (5, 1, 1)))
    arguments = [a.format(odometry=odometry) for a in arguments]
    assert main([str(folder), *arguments, "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, *words)
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").iterdir())


@pytest.mark.slow
def test_refine_reads_the_bag_again_and_reports_its_time(bag, tmp_path):
    out = tmp_path / "results"
    assert main([str(bag), "--gt", str(ground_truth_path(bag)), "--out", str(out), "--quiet", "--refine"]) == 0
    folder = (out / "latest").resolve()
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["frames"] == FRAMES and metrics["timings_s"]["refine"] > 0.0
    assert metrics["ground_truth"]["ate_slam_m"] < 0.3
    assert "refine: true" in (folder / "config.yaml").read_text()
