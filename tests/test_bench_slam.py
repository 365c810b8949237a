"""`sandro-bench slam` wiring, on a few frames of the simulated drive."""

import json

from pipelines.bench import main
from pipelines.bench_slam_bags import bag_experiment
from sandro_slam import SlamConfig


def test_short_run_writes_its_outputs(tmp_path):
    assert main(["slam", "--frames", "25", "--no-kiss-slam", "--no-bags", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["frames"] == 25 and metrics["ate_sandro_slam"] < 0.5
    for name in ("metrics.csv", "trajectories.png", "sandro-slam.tum", "ground_truth.tum", "KISS-ICP.tum"):
        assert (tmp_path / name).is_file()


def test_missing_config_is_a_usage_error(tmp_path, capsys):
    assert main(["slam", "--config", str(tmp_path / "nope.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().err


def test_bag_experiment_runs_a_bag_end_to_end_and_times_reading(tmp_path):
    metrics = bag_experiment(tmp_path, SlamConfig(), seed=0, laps=1, frames=12, formats=("ros2-mcap",), read_scans=3)
    assert metrics["bag_ros2-mcap_ate_sandro_slam"] < 0.3
    assert 0 < metrics["bag_ros2-mcap_read_share"] < 1 and metrics["bag_ros2-mcap_read_realtime_factor_64beam"] > 0
    assert not (tmp_path / "bags").exists()  # the bags are removed
    assert (tmp_path / "sandro-slam_ros2-mcap" / "latest" / "metrics.json").is_file()
