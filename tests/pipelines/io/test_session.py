"""session/ of a sandro-slam results folder: round trip and bad folders (the `results` fixture: tests/pipelines)."""

import json

import numpy as np
import pytest

from pipelines.io.session import read_session
from sandro_slam import Session


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
