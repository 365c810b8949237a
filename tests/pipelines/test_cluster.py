"""Many inputs and many sessions: `sandro-slam` batches and `sandro-merge` in process and on a local Ray."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import pipelines.cluster as cluster
from pipelines.batch import jobs_for
from pipelines.cli.bench import main as bench_main
from pipelines.cli.merge import main as merge_main
from pipelines.cli.slam import main
from pipelines.cluster import ray_map, ray_session
from pipelines.simulation.export import simulate
from sandro_slam import SlamConfig
from sandro_slam.merge.pipeline import serial_map

FRAMES = 30


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> list[Path]:
    """Two short simulated drives and a truncated bag, in the order good, corrupt, good."""
    folder = tmp_path_factory.mktemp("batch")
    good = []
    for seed in (0, 1):
        path = folder / f"drive{seed}.bag"
        simulate(path, "ros1", seed=seed, frames=FRAMES)
        good.append(path)
    corrupt = folder / "corrupt.bag"
    corrupt.write_bytes(good[0].read_bytes()[:3000])
    (folder / "corrupt.bag.gt.tum").write_text((folder / "drive0.bag.gt.tum").read_text())
    return [good[0], corrupt, good[1]]


def _summary(out: Path) -> list[dict[str, str]]:
    with (out / "batch.csv").open() as handle:
        return list(csv.DictReader(handle))


def _loops(out: Path, name: str) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """loops.csv of a run: per loop, its keys, how it was found and whether it was accepted; and its numbers."""
    with open(out / name / "latest" / "loops.csv") as file:
        rows = list(csv.DictReader(file))
    exact = ("source_key", "target_key", "found_by", "inliers", "accepted")
    numbers = [[float(value) for key, value in row.items() if key not in exact] for row in rows]
    return [tuple(row[key] for key in exact) for row in rows], np.array(numbers)


def _poses(out: Path, name: str) -> np.ndarray:
    return np.loadtxt(out / name / "latest" / "poses.tum")


def test_a_corrupt_input_is_reported_and_the_others_finish_then_resume_skips_them(bags, tmp_path, capsys):
    out = tmp_path / "out"
    gt = str(bags[0].parent / "{name}.bag.gt.tum")
    assert main([*map(str, bags), "--workers", "1", "--gt", gt, "--out", str(out), "--quiet"]) == 1
    rows = _summary(out)
    assert [(row["name"], row["status"]) for row in rows] == [("drive0", "done"), ("corrupt", "failed"),
                                                               ("drive1", "done")]  # fmt: skip
    assert "corrupt or truncated bag" in rows[1]["error"]
    assert int(rows[0]["frames"]) == FRAMES and float(rows[0]["ate_slam_m"]) < 0.3
    assert json.loads((out / "batch.json").read_text())[2]["status"] == "done"
    assert "failed" in capsys.readouterr().out

    folders = sorted(p.name for p in (out / "drive0").iterdir())
    assert main([*map(str, bags), "--workers", "1", "--resume", "--out", str(out), "--quiet"]) == 1
    assert [row["status"] for row in _summary(out)] == ["skipped", "failed", "skipped"]
    assert sorted(p.name for p in (out / "drive0").iterdir()) == folders  # nothing ran again


def test_ray_workers_give_the_serial_results(bags, tmp_path):
    pytest.importorskip("ray")
    serial, parallel = tmp_path / "serial", tmp_path / "ray"
    good = [str(bags[0]), str(bags[2])]
    one_thread = ["--threads-per-task", "1", "--quiet"]
    assert main([*good, "--workers", "1", "--out", str(serial), *one_thread]) == 0
    assert main([*good, str(bags[1]), "--workers", "2", "--out", str(parallel), *one_thread]) == 1
    assert [row["status"] for row in _summary(parallel)] == ["done", "done", "failed"]
    for name in ("drive0", "drive1"):  # equal to 1e-6: the odometry's last bits differ between a Ray worker and here
        np.testing.assert_allclose(_poses(parallel, name), _poses(serial, name), rtol=0.0, atol=1e-6)
        serial_loops, serial_numbers = _loops(serial, name)
        parallel_loops, parallel_numbers = _loops(parallel, name)
        assert parallel_loops == serial_loops
        np.testing.assert_allclose(parallel_numbers, serial_numbers, rtol=1e-6, atol=1e-6)


def test_more_workers_without_ray_say_how_to_install_it(bags, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cluster, "ray_available", lambda: False)
    assert main([str(bags[0]), str(bags[2]), "--workers", "2", "--out", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "pip install" in err and "\n" not in err and "Traceback" not in err


def test_jobs_get_unique_names_and_need_a_pattern_for_several_inputs(tmp_path):
    inputs = [tmp_path / "a" / "drive.bag", tmp_path / "b" / "drive.bag", tmp_path / "scans"]
    (tmp_path / "scans").mkdir()
    jobs = jobs_for(inputs, tmp_path / "out", gt="truth/{name}.tum", config=SlamConfig())
    assert [job.out.name for job in jobs] == ["drive", "drive-2", "scans"]
    assert [job.gt for job in jobs] == ["truth/drive.tum", "truth/drive.tum", "truth/scans.tum"]
    with pytest.raises(ValueError, match="{name}"):
        jobs_for(inputs, tmp_path / "out", gt="truth.tum", config=SlamConfig())
    assert jobs_for(inputs[:1], tmp_path / "out", gt="truth.tum", config=SlamConfig())[0].gt == "truth.tum"
    jobs = jobs_for(inputs, tmp_path / "out", odometry="/lio/odometry", config=SlamConfig())  # a topic of each bag
    assert [job.odometry for job in jobs] == ["/lio/odometry"] * 3


@pytest.mark.slow
def test_sandro_merge_on_ray_workers_gives_the_serial_merge(results, tmp_path):
    pytest.importorskip("ray")
    folders = [str(results[0][0]), str(results[1][0])]
    transforms = []
    for name, workers in (("serial", "1"), ("ray", "2")):
        out = tmp_path / name
        assert merge_main([*folders, "--out", str(out), "--workers", workers, "--threads-per-task", "1"]) == 0
        transforms.append((out / "transforms.yaml").read_text())
    assert transforms[0] == transforms[1]


def test_ray_map_shares_arguments_and_keeps_the_order():
    pytest.importorskip("ray")
    big = np.arange(1000.0)
    with ray_session(2):
        assert ray_map(np.dot, [(big, big), (big, 2 * big), (big, big)]) == [serial_map(np.dot, [(big, b)])[0]
                                                                             for b in (big, 2 * big, big)]  # fmt: skip


@pytest.mark.slow
def test_the_batch_benchmark_runs_and_finds_equal_results(tmp_path, capsys):
    pytest.importorskip("ray")
    out = tmp_path / "bench"
    args = ["batch", "--bags", "1", "--frames", "20", "--ways", "serial-1t,ray1-1t", "--sessions", "0"]
    assert bench_main([*args, "--cache", str(tmp_path / "cache"), "--out", str(out)]) == 0
    with (out / "batch.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [(row["way"], row["done"], row["equal_to_serial_1t"]) for row in rows] == [
        ("serial-1t", "1", "True"),
        ("ray1-1t", "1", "True"),
    ]
    assert "ray1-1t" in capsys.readouterr().out


@pytest.mark.slow
def test_ctrl_c_cancels_a_ray_batch_and_lists_what_did_not_finish(tmp_path, interrupted_slam):
    pytest.importorskip("ray")
    long = tmp_path / "long.bag"
    simulate(long, "ros1", frames=200)
    out = tmp_path / "out"
    arguments = [str(long), str(long), "--workers", "2", "--out", str(out), "--quiet"]
    returncode, stderr = interrupted_slam(arguments, lambda: bool(list(out.glob("long*/2*"))), wait=120)  # a task runs
    assert returncode == 130, stderr
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == "sandro-slam: aborted"
    assert [row["status"] for row in _summary(out)] == ["cancelled", "cancelled"]
