"""`sandro-bench posegraph` on small pose graphs written here: outputs, outlier rejection, seeding, errors."""

import csv
from pathlib import Path

import gtsam
import numpy as np
import pytest

from pipelines.bench.posegraph import (
    CHAIN_PRIOR_SIGMA,
    RESULT_FIELDS,
    inject_outliers,
    load_problem,
    odometry_initial,
    reference,
)
from pipelines.cli.bench import main

LAP = 30  # poses per lap of the circle
SIGMA_T, SIGMA_R = 0.05, 0.01  # [m], [rad]: std in the written information matrices
NOISE_SHARE = 0.5  # measurements get half that std: no real loop lands in the chi-square tail


def _circle(laps: int = 2) -> list[gtsam.Pose3]:
    """Poses on a 10 m circle, driven `laps` times, gently rising and falling."""
    poses = []
    for i in range(laps * LAP):
        angle = 2 * np.pi * i / LAP
        position = [10 * np.cos(angle), 10 * np.sin(angle), 0.5 * np.sin(3 * angle)]
        poses.append(gtsam.Pose3(gtsam.Rot3.Yaw(angle + np.pi / 2), np.array(position)))
    return poses


def _g2o_information(diagonal: list[float]) -> str:
    """The upper triangle of a diagonal information matrix, row by row, as g2o writes it."""
    return " ".join(str(diagonal[i] if i == j else 0) for i in range(len(diagonal)) for j in range(i, len(diagonal)))


def _noisy(rng: np.random.Generator, pose: gtsam.Pose3, share: float = NOISE_SHARE) -> gtsam.Pose3:
    xi = share * np.concatenate([rng.normal(scale=SIGMA_R, size=3), rng.normal(scale=SIGMA_T, size=3)])
    return pose.compose(gtsam.Pose3.Expmap(xi))


def _write_g2o(path: Path, dim: int, seed: int = 0, noise_share: float = NOISE_SHARE) -> None:
    """Odometry along two laps plus a loop between every pose of the second lap and the first, with the
    odometry chain as initial values; 3D (EDGE_SE3:QUAT) or 2D (EDGE_SE2, the circle in the plane). The
    measurements' noise is `noise_share` times the stated standard deviations (0: exact)."""
    rng = np.random.default_rng(seed)
    truth = _circle()
    edges = [(i, i + 1) for i in range(len(truth) - 1)] + [(i, i + LAP) for i in range(LAP)]
    measured = {(a, b): _noisy(rng, truth[a].between(truth[b]), noise_share) for a, b in edges}
    chain = [truth[0]]
    for i in range(len(truth) - 1):
        chain.append(chain[-1].compose(measured[(i, i + 1)]))
    lines = []
    if dim == 3:
        info = _g2o_information([1 / SIGMA_T**2] * 3 + [1 / SIGMA_R**2] * 3)  # g2o order [t, r]
        for i, pose in enumerate(chain):
            q = pose.rotation().toQuaternion()
            t = " ".join(map(str, pose.translation()))
            lines.append(f"VERTEX_SE3:QUAT {i} {t} {q.x()} {q.y()} {q.z()} {q.w()}")
        for (a, b), pose in measured.items():
            q = pose.rotation().toQuaternion()
            t = " ".join(map(str, pose.translation()))
            lines.append(f"EDGE_SE3:QUAT {a} {b} {t} {q.x()} {q.y()} {q.z()} {q.w()} {info}")
    else:
        info = _g2o_information([1 / SIGMA_T**2] * 2 + [1 / SIGMA_R**2])
        for i, pose in enumerate(chain):
            lines.append(f"VERTEX_SE2 {i} {pose.x()} {pose.y()} {pose.rotation().yaw()}")
        for (a, b), pose in measured.items():
            lines.append(f"EDGE_SE2 {a} {b} {pose.x()} {pose.y()} {pose.rotation().yaw()} {info}")
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture
def data(tmp_path: Path) -> Path:
    folder = tmp_path / "graphs"
    folder.mkdir()
    _write_g2o(folder / "circle3d.g2o", 3)
    _write_g2o(folder / "circle2d.g2o", 2)
    return folder


def _rows(out: Path) -> list[dict[str, str]]:
    with (out / "results.csv").open() as handle:
        return list(csv.DictReader(handle))


@pytest.mark.parametrize("graph", ["circle3d", "circle2d"])
def test_quick_run_writes_outputs_and_gnc_rejects_the_injected_loops(data, tmp_path, capsys, graph):
    out = tmp_path / "bench"
    code = main(["posegraph", "--quick", "--data", str(data), "--graphs", graph, "--rates", "10,50",
                 "--methods", "gnc_tls,gnc_gm,lm", "--out", str(out)])  # fmt: skip
    assert code == 0
    rows = _rows(out)
    assert list(rows[0]) == RESULT_FIELDS and len(rows) == 2 * 3
    assert {(row["rate_pct"], row["n_outliers"]) for row in rows} == {("10", "3"), ("50", "15")}
    for row in rows:
        if row["method"] == "gnc_tls":
            assert (row["precision"], row["recall"], row["real_rejected"]) == ("1", "1", "0"), row
            assert row["within_1pct"] == "1" and float(row["pose_rel"]) < 1e-4, row
            assert abs(float(row["tls_rel"])) < 1e-6, row  # the clean optimum's loops: its TLS cost
        if row["method"] == "gnc_gm":  # soft weights: every injected loop below 0.5, the poses close
            assert row["recall"] == "1" and float(row["pose_rel"]) < 0.01, row
    plain = [row for row in rows if row["method"] == "lm" and row["rate_pct"] == "50"]
    assert float(plain[0]["trans_rmse_m"]) > 0.1  # the injected loops do hurt least squares
    assert float(plain[0]["tls_rel"]) > 0.1  # and its TLS cost
    assert (out / "reference.csv").is_file() and (out / "settings.json").is_file()
    for plot in ("posegraph.png", "posegraph_time.png"):
        assert (out / plot).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(float(row["time_x_ref"]) > 0 for row in rows)
    assert graph in capsys.readouterr().out


def test_a_graph_of_exact_measurements_has_no_cost_rel_and_is_judged_by_its_poses(tmp_path):
    data = tmp_path / "graphs"
    data.mkdir()
    _write_g2o(data / "exact.g2o", 2, noise_share=0.0)
    out = tmp_path / "bench"
    code = main(["posegraph", "--data", str(data), "--rates", "30", "--methods", "gnc_tls,lm", "--out", str(out)])
    assert code == 0
    rows = {row["method"]: row for row in _rows(out)}
    assert rows["gnc_tls"]["cost_rel"] == rows["lm"]["cost_rel"] == "nan"  # relative to a cost of numerically 0
    assert rows["gnc_tls"]["within_1pct"] == "1" and rows["lm"]["within_1pct"] == "0"


def test_profile_lists_where_each_run_went(data, tmp_path):
    out = tmp_path / "bench"
    code = main(["posegraph", "--quick", "--data", str(data), "--graphs", "circle2d", "--rates", "10,50",
                 "--methods", "gnc_tls,lm", "--profile", "--out", str(out)])  # fmt: skip
    assert code == 0
    with (out / "profile.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    for rate in ("10", "50"):
        mine = {row["function"]: row for row in rows if row["rate_pct"] == rate and row["method"] == "gnc_tls"}
        top = next(row for function, row in mine.items() if function.endswith("(robust_optimize)"))
        assert top["function"].startswith("robust_backend.py:") and top["calls"] == "1"
        assert 0.5 < float(top["share"]) <= 1.0
        assert int(mine["gtsam.optimize"]["calls"]) >= 1  # the back end's solves
        assert all(float(row["time_s"]) <= float(top["time_s"]) for row in mine.values())
    plain = [row for row in rows if row["method"] == "lm"]
    assert plain and all(row["function"] == "gtsam.optimize" for row in plain)


@pytest.mark.parametrize("dim", [3, 2])
def test_the_reference_starts_from_the_chordal_relaxation_where_the_file_holds_identity_vertices(tmp_path, dim):
    path = tmp_path / "identity.g2o"
    _write_g2o(path, dim)
    identity = " 0 0 0 0 0 0 1" if dim == 3 else " 0 0 0"
    lines = [" ".join(line.split()[:2]) + identity if line.startswith("VERTEX") else line
             for line in path.read_text().splitlines()]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    ref, elapsed, details = reference(load_problem(path))
    assert details["start"] == "chordal" and elapsed == details["time_chordal_s"]
    assert ref.cost == details["cost_chordal"] < 0.01 * details["cost_file"]  # LM from identity: a local minimum
    assert ref.variance_factor < 1.0  # the measurements carry half the written noise
    assert details["start_spread"] > 0.01  # the other start's solution: a local minimum elsewhere


def test_injected_loops_are_seeded_and_skip_neighbours(data):
    problem = load_problem(data / "circle3d.g2o")
    first, again = inject_outliers(problem, 50, seed=3), inject_outliers(problem, 50, seed=3)
    other = inject_outliers(problem, 50, seed=4)
    assert len(first) == round(0.5 * len(problem.loops))
    assert [f.keys() for f in first] == [f.keys() for f in again] != [f.keys() for f in other]
    assert all(np.allclose(a.measured().matrix(), b.measured().matrix()) for a, b in zip(first, again))
    assert all(abs(a - b) > 1 for a, b in (f.keys() for f in first))
    assert all(np.linalg.norm(f.measured().translation()) <= 5.0 for f in first)


def test_a_gap_in_the_odometry_starts_a_second_chain_with_a_weak_prior(data, tmp_path):
    lines = (data / "circle3d.g2o").read_text().splitlines()
    gap = [line for line in lines if not line.startswith(f"EDGE_SE3:QUAT {LAP - 1} {LAP} ")]
    assert len(gap) == len(lines) - 1
    path = tmp_path / "sessions.g2o"
    path.write_text("\n".join(gap) + "\n")
    problem = load_problem(path)
    assert [prior.keys()[0] for prior in problem.priors] == [0, LAP]
    assert problem.priors[1].noiseModel().sigmas() == pytest.approx([CHAIN_PRIOR_SIGMA] * 6)
    assert len(problem.odometry) == 2 * LAP - 2 and len(problem.loops) == LAP
    chained = odometry_initial(problem)  # the second chain starts again at the file's pose
    assert chained.size() == 2 * LAP and chained.atPose3(LAP).equals(problem.initial.atPose3(LAP), 1e-9)


def test_a_graph_without_consecutive_edges_is_refused_with_one_line(data, tmp_path, capsys):
    lines = (data / "circle3d.g2o").read_text().splitlines()
    only_loops = [
        line for line in lines if not line.startswith("EDGE") or abs(int(line.split()[1]) - int(line.split()[2])) != 1
    ]
    (data / "circle3d.g2o").write_text("\n".join(only_loops) + "\n")
    assert main(["posegraph", "--data", str(data), "--graphs", "circle3d", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "odometry chain" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()  # refused before anything is written


@pytest.mark.parametrize(
    "args, message",
    [
        (["--data", "/no/such/folder"], "no such folder"),
        (["--graphs", "nope"], "unknown or no graphs"),
        (["--methods", "nope"], "unknown or no methods"),
        (["--rates", "x"], "expected a comma list of integers"),
        (["--info-scale", "0"], "expected positive numbers or 'auto'"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(data, tmp_path, capsys, args, message):
    defaults = [] if "--data" in args else ["--data", str(data)]
    assert main(["posegraph", *defaults, "--out", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
