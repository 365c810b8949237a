"""`sandro-merge`: two results folders joined, bad inputs in one line and nothing written."""

import json

import pytest

from pipelines.cli.merge import main
from pipelines.simulation.export import simulate


@pytest.mark.slow
def test_sandro_merge_on_two_results_folders(results, tmp_path, capsys):
    out = tmp_path / "merged"
    assert main([str(results[0][0]), str(results[1][0]), "--out", str(out)]) == 0
    for name in ("transforms.yaml", "map.ply", "graph.g2o", "trajectories.png", "summary.json"):
        assert (out / name).is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["joined"]) == 2 and summary["inter_session_loops_accepted"] >= 3
    assert len(list((out / "trajectories").glob("*.tum"))) == 2
    assert "2 sessions joined" in capsys.readouterr().out


def test_missing_session_folder_is_one_line(tmp_path, capsys):
    assert main([str(tmp_path / "nope"), str(tmp_path / "nope2"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "no such session folder" in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_folder_of_another_tool_is_one_line(tmp_path, capsys):
    for name in ("x", "y"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text("{}")
    assert main([str(tmp_path / "x"), str(tmp_path / "y"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "not a sandro-slam results folder" in err and err.count("\n") == 1


def test_non_empty_out_is_refused(tmp_path, capsys):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    assert main([str(tmp_path), str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_sandro_merge_on_two_front_end_bags_runs_on_their_odometry_topic(tmp_path, capsys):
    bags = [tmp_path / "first.bag", tmp_path / "second.bag"]
    for bag, drift in zip(bags, (0.0, 0.01)):  # the same street, odometry drifting differently
        simulate(bag, "ros1", frames=50, odometry_topic="/odometry", drift=drift)
    out = tmp_path / "merged"
    assert main([*map(str, bags), "--odometry", "/odometry", "--out", str(out)]) == 0
    assert len(json.loads((out / "summary.json").read_text())["joined"]) == 2
    runs = [path for path in (out / "sessions").glob("*/metrics.json") if path.parent.name != "latest"]
    assert len(runs) == 2 and all(json.loads(path.read_text())["odometry"] == "given" for path in runs)
    assert "also holds poses" not in capsys.readouterr().err


def test_an_odometry_that_is_not_a_topic_is_one_line(results, tmp_path, capsys):
    folders = [str(results[0][0]), str(results[1][0])]
    assert main([*folders, "--odometry", "poses.tum", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "--odometry poses.tum: not a topic name nor tf:FRAME" in err and err.count("\n") == 1
