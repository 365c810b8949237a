"""`sandro-bench slam` wiring, on a few frames of the simulated drive."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipelines.bench.bags import bag_experiment
from pipelines.bench.slam import keyframe_floor, loop_errors, loops_against_truth, submap_frames
from pipelines.cli.bench import main
from sandro_slam import SlamConfig


@pytest.mark.slow
def test_short_run_writes_its_outputs(tmp_path):
    assert main(["slam", "--frames", "25", "--no-kiss-slam", "--no-bags", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["frames"] == 25 and metrics["ate_sandro_slam"] < 0.5
    assert metrics["given_0.5pct_ate_odometry"] > 0.0 and metrics["given_0.05pct_ate_sandro_slam"] < 0.5
    assert metrics["given_0.5pct_raw_ate_sandro_slam"] < 0.5
    lost, cut, repeated = (metrics[f"damaged_frames_{what}"] for what in ("lost", "cut", "repeated"))
    assert (lost, cut, repeated) == (2, 1, 1) and metrics["damaged_frames_skipped"] == cut + repeated
    assert metrics["damaged_ate_sandro_slam"] < 0.5
    for name in ("metrics.csv", "trajectories.png", "sandro-slam.tum", "ground_truth.tum", "KISS-ICP.tum"):
        assert (tmp_path / name).is_file()


def test_missing_config_is_a_usage_error(tmp_path, capsys):
    assert main(["slam", "--config", str(tmp_path / "nope.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().err


def test_bag_experiment_runs_a_bag_end_to_end_and_times_reading(tmp_path):
    metrics = bag_experiment(tmp_path, SlamConfig(), seed=0, laps=1, frames=12, formats=("ros2-mcap",), read_scans=3)
    for name in ("ros2-mcap", "ros1_livox"):  # the same drive as PointCloud2 and as Livox CustomMsg
        assert metrics[f"bag_{name}_ate_sandro_slam"] < 0.3
        assert 0 < metrics[f"bag_{name}_read_share"] < 1 and metrics[f"bag_{name}_read_realtime_factor_64beam"] > 0
        assert (tmp_path / f"sandro-slam_{name}" / "latest" / "metrics.json").is_file()
    assert metrics["bag_ros1_livox_ate_kiss_icp"] == pytest.approx(metrics["bag_ros2-mcap_ate_kiss_icp"], abs=0.01)
    assert 0 < metrics["bag_ros2_lio_ate_given"] < 0.3 and metrics["bag_ros2_lio_ate_sandro_slam"] < 0.3
    assert "bag_ros2_lio_read_realtime_factor_64beam" not in metrics
    assert not (tmp_path / "bags").exists()  # the bags are removed


def _poses(xs):
    poses = np.tile(np.eye(4), (len(xs), 1, 1))
    poses[:, 0, 3] = xs
    return poses


def test_keyframe_floor_is_the_error_no_rigid_move_per_keyframe_removes():
    truth = _poses(np.arange(6.0))
    keyframes = [SimpleNamespace(key=0), SimpleNamespace(key=1)]
    of_frame = np.array([0, 0, 0, 1, 1, 1])
    shifted = truth.copy()
    shifted[:3, :3, 3] += [5.0, -2.0, 1.0]  # keyframe 0 off by one rigid move, keyframe 1 by another
    shifted[3:, 1, 3] += 3.0
    result = SimpleNamespace(keyframes=keyframes, keyframe_of_frame=of_frame, odometry_poses=shifted)
    assert keyframe_floor(result, truth) == pytest.approx(0.0, abs=1e-9)
    bent = truth.copy()
    bent[1, 1, 3] += 0.3  # the middle scan of keyframe 0 off the line its neighbours lie on
    result.odometry_poses = bent
    floor = keyframe_floor(result, truth)
    assert 0.0 < floor < 0.3 / np.sqrt(6)  # the fit spreads the bend over the keyframe's three scans


def test_loops_against_truth_tells_wrong_loops_from_real_ones():
    truth = _poses(np.arange(0.0, 60.0, 10.0))  # six keyframes 10 m apart, one scan each
    keyframes = [SimpleNamespace(key=k, anchor_frame=k) for k in range(6)]

    def loop(target, source, offset, weight):
        measured = np.linalg.inv(truth[target]) @ truth[source]
        measured[0, 3] += offset
        return SimpleNamespace(target_key=target, source_key=source, T_target_source=measured, weight=weight)

    loops = [
        loop(0, 3, 0.02, 1.0),
        loop(1, 4, 0.04, 1.0),
        loop(2, 5, 0.06, 0.0),  # real, one rejected
        loop(0, 5, 12.0, 0.0),
        loop(1, 5, -8.0, 1.0),
    ]  # wrong (aliased streets), one kept
    result = SimpleNamespace(
        keyframes=keyframes, loops=loops, keyframe_of_frame=np.arange(6), T_keyframe_frame=np.tile(np.eye(4), (6, 1, 1))
    )
    metrics = loops_against_truth(result, truth)
    assert metrics["loops_wrong"] == 2 and metrics["loops_wrong_rejected"] == 1
    assert metrics["loops_wrong_kept_submap_frames"] == 1
    assert metrics["loops_real_rejected"] == 1
    assert metrics["loop_error_median_m"] == pytest.approx(0.04)
    assert metrics["loop_error_median_deg"] == pytest.approx(0.0, abs=1e-6)


def test_a_loop_right_about_submaps_whose_anchor_is_off_is_told_apart():
    truth = _poses(np.arange(0.0, 40.0, 1.0))  # 40 scans 1 m apart: keyframes 0 and 1 of 20 scans each
    keyframes = [SimpleNamespace(key=k, anchor_frame=20 * k) for k in range(2)]
    of_frame = np.repeat([0, 1], 20)
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
    odometry = truth.copy()
    odometry[20] = truth[20] @ turned  # keyframe 1's anchor scan alone registered 3 deg off
    T_keyframe_frame = np.stack([np.linalg.inv(odometry[20 * k]) @ odometry[i] for i, k in enumerate(of_frame)])
    # Its submap is built in the anchor's frame: a registration of the submaps is off the anchors' truth by the turn.
    measured = np.linalg.inv(truth[0]) @ truth[20] @ turned
    loop = SimpleNamespace(target_key=0, source_key=1, T_target_source=measured, weight=1.0)
    result = SimpleNamespace(
        keyframes=keyframes, loops=[loop], keyframe_of_frame=of_frame, T_keyframe_frame=T_keyframe_frame
    )
    assert loop_errors(result, truth)[0, 0] == pytest.approx(3.0)
    assert loop_errors(result, truth, submap_frames(result, truth))[0, 0] < 0.2  # 1 of 20 scans in the mean
    metrics = loops_against_truth(result, truth)
    assert metrics["loops_wrong"] == 1 and metrics["loops_wrong_kept_submap_frames"] == 0
