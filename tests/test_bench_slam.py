"""`sandro-bench slam` wiring, on a few frames of the simulated drive."""

import json

from pipelines.bench import main


def test_short_run_writes_its_outputs(tmp_path):
    assert main(["slam", "--frames", "25", "--no-kiss-slam", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["frames"] == 25 and metrics["ate_sandro_slam"] < 0.5
    for name in ("metrics.csv", "trajectories.png", "sandro-slam.tum", "ground_truth.tum", "KISS-ICP.tum"):
        assert (tmp_path / name).is_file()


def test_missing_config_is_a_usage_error(tmp_path, capsys):
    assert main(["slam", "--config", str(tmp_path / "nope.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().err
