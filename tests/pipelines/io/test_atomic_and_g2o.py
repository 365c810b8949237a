"""Result files: atomic writes, results folders, g2o."""

import gtsam
import numpy as np
import pytest

from pipelines.io.atomic import atomic_path, link_latest, new_run_folder, write_text_atomic
from pipelines.io.g2o import read_g2o, write_g2o


def test_atomic_write_replaces_only_on_success(tmp_path):
    target = tmp_path / "a.txt"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_run_folders_are_new_and_latest_follows(tmp_path):
    first, second = new_run_folder(tmp_path / "runs"), new_run_folder(tmp_path / "runs")
    assert first != second and first.is_dir() and second.is_dir()
    link_latest(first)
    link_latest(second)
    assert (tmp_path / "runs" / "latest").resolve() == second.resolve()


def test_g2o_round_trip_strips_robust_models_and_priors(tmp_path):
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    poses = [gtsam.Pose3(), gtsam.Pose3(gtsam.Rot3.Yaw(0.3), gtsam.Point3(1, 0, 0))]
    for key, pose in enumerate(poses):
        values.insert(key, pose)
    graph.add(gtsam.PriorFactorPose3(0, poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-2, 2e-2, 3e-2])
    model = gtsam.noiseModel.Gaussian.Covariance(covariance)
    graph.add(gtsam.BetweenFactorPose3(0, 1, poses[0].between(poses[1]), model))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(1.0)
    robust = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(6, 0.5))
    graph.add(gtsam.BetweenFactorPose3(1, 0, gtsam.Pose3(), robust))
    assert write_g2o(tmp_path / "g.g2o", graph, values) == 2
    read, read_values = read_g2o(tmp_path / "g.g2o")
    assert read.size() == 2 and read_values.size() == 2
    np.testing.assert_allclose(read.at(0).noiseModel().covariance(), covariance, rtol=1e-5)  # [r, t] order kept
    np.testing.assert_allclose(read_values.atPose3(1).matrix(), poses[1].matrix(), atol=1e-5)  # 6 digits


def test_g2o_reading_errors(tmp_path):
    with pytest.raises(ValueError, match="no such"):
        read_g2o(tmp_path / "missing.g2o")
    (tmp_path / "x.g2o").write_text("hello\n")
    with pytest.raises(ValueError, match="not a 3D g2o"):
        read_g2o(tmp_path / "x.g2o")
