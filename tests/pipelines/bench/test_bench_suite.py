"""`sandro-bench suite`: the sequences it holds, its targets, and a smoke run on a few frames."""

import json
from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from pipelines.bench.suite import check_targets, floor_pairs, overlapping
from pipelines.cli.bench import main
from pipelines.simulation.suite import HELD_OUT, SUITE, cached_frames


def test_the_suite_varies_what_breaks_slam():
    assert len(SUITE) >= 12 and len({spec.name for spec in SUITE}) == len(SUITE)
    assert set(Counter(spec.site for spec in SUITE)) == {"city", "garage", "campus", "office"}
    assert set(Counter(spec.sensor for spec in SUITE)) == {"vlp16", "spinning32", "os128", "avia", "mid360"}
    assert {"car", "walk"} <= {spec.platform for spec in SUITE}
    assert {spec.start for spec in SUITE} == {"rest", "moving"}
    assert sum(spec.time_field != "per_point" for spec in SUITE) >= 2
    assert any("back" in spec.path for spec in SUITE)  # revisits in the opposite direction
    assert len({spec.cache_key() for spec in SUITE}) == len(SUITE)


def test_the_held_out_sequences_are_no_suite_sequence_again(capsys):
    """Each held-out sequence is another world (seed) of its site, driven with a path, sensor, platform and time
    field the suite does not combine, and `--held-out --list` names them all."""

    def combination(spec):
        return spec.site, spec.path, spec.sensor, spec.platform, spec.time_field

    combinations = {combination(spec) for spec in SUITE}
    for spec in HELD_OUT:
        assert spec.seed != 0 and combination(spec) not in combinations
    assert {spec.site for spec in HELD_OUT} == {spec.site for spec in SUITE}
    keys = {spec.cache_key() for spec in HELD_OUT}
    assert len(keys) == len(HELD_OUT) and not keys & {spec.cache_key() for spec in SUITE}
    assert main(["suite", "--held-out", "--list"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == [spec.name for spec in HELD_OUT]


def test_cached_frames_are_the_simulated_ones(tmp_path):
    spec = next(spec for spec in SUITE if spec.time_field == "none_deskewed")
    frames = list(cached_frames(spec, tmp_path, frames=3))
    again = list(cached_frames(spec, tmp_path, frames=3))  # read back from the cache
    sequence = spec.sequence()
    assert len(frames) == 3 and len(list(tmp_path.iterdir())) == 1
    for k, (frame, cached) in enumerate(zip(frames, again)):
        direct = spec.scan(sequence, k)
        assert frame.timestamp == direct.timestamp and len(frame.times) == 0
        np.testing.assert_allclose(frame.points, direct.points, atol=1e-4)  # float32 on disk
        np.testing.assert_array_equal(frame.points, cached.points)


def test_targets_name_every_miss():
    row = dict(sequence="a", ate_sandro_slam=0.3, ate_kiss_slam=0.2, ate_perfect_loop_floor=0.2, revisits=True,
               loops_wrong_kept=1, loops_real_rejected=1, fps_sandro_slam=10.0, fps_kiss_slam=20.0)  # fmt: skip
    misses = check_targets([row, {**row, "sequence": "b"}])
    assert len(misses) == 2 * 3 + 2  # per row: KISS-SLAM, floor, wrong loop; real loops on two; frames/s
    good = {**row, "ate_sandro_slam": 0.1, "loops_wrong_kept": 0, "loops_real_rejected": 0, "fps_sandro_slam": 30.0}
    assert check_targets([good]) == []
    assert check_targets([{**good, "revisits": False, "ate_perfect_loop_floor": 0.01}]) == []
    by_default = {
        **row,
        "default_ate_sandro_slam": 0.1,
        "default_loops_wrong_kept": 0,
        "default_loops_real_rejected": 0,
    }
    assert len(check_targets([by_default])) == 1  # the second pass by default: only the frames/s of the first
    refined = {**good, "ate_kiss_icp": 1.0, "ate_sandro_slam_refined": 0.15, "refine_time_share": 0.8}
    assert check_targets([refined]) == []
    assert check_targets([{**refined, "ate_sandro_slam_refined": 0.3, "refine_time_share": 1.5}]) == [
        "refined: median ATE 0.30x KISS-ICP's (target <= 0.2x)",
        "refined: median time 2.50x the first pass's (target <= 2x)",
    ]


def test_floor_pairs_are_near_and_far_apart_and_the_registrable_ones_share_their_submaps():
    """Four keyframes on a line, 10 m apart in travel; 0 and 3 come back to the same place. Keyframe 2's submap
    holds another part of the world than 0's (a narrow view the other way)."""
    rng = np.random.default_rng(0)
    ahead = rng.uniform([0.0, -5.0, -1.0], [10.0, 5.0, 1.0], size=(2000, 3))  # [m] in front of the sensor
    truth = np.tile(np.eye(4), (4, 1, 1))
    truth[:, 0, 3] = [0.0, 8.0, 1.0, 0.5]  # [m] the anchors' true positions: 2 and 3 back near 0
    truth[2, :3, :3] = np.diag([-1.0, -1.0, 1.0])  # keyframe 2 looks the other way
    keyframes = [
        SimpleNamespace(key=k, anchor_frame=k, travelled=10.0 * k, points=(seen - truth[k, :3, 3]) @ truth[k, :3, :3])
        for k, seen in enumerate([ahead, ahead, ahead * [-1.0, 1.0, 1.0], ahead])
    ]  # each submap in its keyframe's frame: the points ahead of keyframe 0, keyframe 2's those behind it
    config = SimpleNamespace(loops=SimpleNamespace(radius=2.0, exclude_recent=15.0),
                             keyframes=SimpleNamespace(submap_voxel=0.5))  # fmt: skip
    result = SimpleNamespace(keyframes=keyframes, config=config, keyframe_of_frame=np.arange(4))  # a scan each
    pairs = floor_pairs(result, truth)
    assert pairs == [(0, 2), (0, 3)]  # 1 and 3: 7.5 m apart
    assert overlapping(result, truth, pairs) == [(0, 3)]  # 2 saw nothing of what 0 saw


@pytest.mark.slow
def test_smoke_run_writes_its_outputs(tmp_path):
    out = tmp_path / "out"
    argv = ["suite", "--sequences", "office_16_rooms_raw", "--frames", "40", "--no-kiss-slam"]
    assert main([*argv, "--cache", str(tmp_path / "cache"), "--out", str(out)]) == 0
    rows = json.loads((out / "suite.json").read_text())
    assert [row["sequence"] for row in rows] == ["office_16_rooms_raw"] and rows[0]["frames"] == 40
    assert rows[0]["ate_sandro_slam"] < 0.5 and rows[0]["scale"] < 0.5
    assert rows[0]["ate_perfect_registration_floor"] < 0.5
    for name in (
        "suite.csv",
        "suite.png",
        "office_16_rooms_raw/trajectories.png",
        "office_16_rooms_raw/sandro_slam.tum",
    ):  # noqa: E501
        assert (out / name).is_file()


def test_unknown_sequence_is_a_usage_error(tmp_path, capsys):
    assert main(["suite", "--sequences", "nowhere", "--out", str(tmp_path)]) == 2
    assert "unknown or no sequences" in capsys.readouterr().err
