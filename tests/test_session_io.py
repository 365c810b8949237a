"""session/ of a sandro-slam results folder: round trip, bad folders, and sandro-merge on two of them."""

import json

import numpy as np
import pytest

from pipelines.merge import main
from pipelines.session_io import read_session, write_session
from pipelines.simulation import simulate_sequence
from sandro_slam import OfflineSlam, Session, SlamConfig


def _run(start_distance: float, frames: int = 50):
    sequence = simulate_sequence(seed=0, frames=frames, start_distance=start_distance)
    return OfflineSlam(SlamConfig()).run((f.timestamp, f.points, f.times) for f in sequence.frames())


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Two results folders of short drives along the same street, the second starting 25 m further on."""
    folders = []
    for name, start in (("first", 0.0), ("second", 25.0)):
        folder = tmp_path_factory.mktemp(name)
        result = _run(start)
        write_session(folder, result)
        folders.append((folder, result))
    return folders


def test_round_trip(results):
    folder, result = results[0]
    session = read_session(folder)
    expected = Session.from_result(result, "x")
    assert session.keys == expected.keys and len(session.edges) == len(expected.edges)
    assert np.allclose(session.frame_poses(), result.poses, atol=1e-3)
    for mine, theirs in zip(session.edges, expected.edges):
        assert mine.kind == theirs.kind and mine.accepted == theirs.accepted
        assert np.allclose(mine.covariance, theirs.covariance, rtol=1e-4, atol=1e-12)
    for key in session.keys:
        assert np.allclose(session.submaps[key], expected.submaps[key], atol=1e-4)


def test_missing_session_file(results, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(results[0][0], copy)
    (copy / "session" / "frames.csv").unlink()
    with pytest.raises(ValueError, match="session/frames.csv is missing"):
        read_session(copy)


def test_wrong_format_marker(results, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(results[0][0], copy)
    (copy / "session" / "session.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="not a sandro-slam session"):
        read_session(copy)


def test_sandro_merge_on_two_results_folders(results, tmp_path, capsys):
    out = tmp_path / "merged"
    assert main([str(results[0][0]), str(results[1][0]), "--out", str(out)]) == 0
    for name in ("transforms.yaml", "map.ply", "graph.g2o", "trajectories.png", "summary.json"):
        assert (out / name).is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["joined"]) == 2 and summary["inter_session_loops_accepted"] >= 3
    assert len(list((out / "trajectories").glob("*.tum"))) == 2
    assert "2 sessions joined" in capsys.readouterr().out
