"""A quick `sandro-bench registration` run on the synthetic part writes its CSVs and plot."""

import csv

import pytest

from pipelines.bench.registration import OUTLIER_KINDS, OUTLIER_RATES, TRIAL_FIELDS
from pipelines.cli.bench import main

SOLVERS = "ransac_1e3,gnc_tls"  # fast ones: a smoke test of the harness, not of the solvers


def test_quick_synthetic_run_writes_csv_and_png(tmp_path, capsys):
    out = tmp_path / "bench"
    code = main(["registration", "--quick", "--parts", "synthetic", "--trials", "2", "--solvers", SOLVERS,
                 "--out", str(out)])  # fmt: skip
    assert code == 0
    with (out / "trials.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == TRIAL_FIELDS
    assert len(rows) == len(OUTLIER_KINDS) * len(OUTLIER_RATES) * 2 * 2
    assert {row["solver"] for row in rows} == set(SOLVERS.split(","))
    zero_outliers = [row for row in rows if float(row["case"]) == 0.0]
    assert all(row["success_10deg_1m"] == "1" for row in zero_outliers)
    with (out / "summary.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == len(OUTLIER_KINDS) * len(OUTLIER_RATES) * 2
    assert (out / "registration.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "synthetic, uniform outliers" in capsys.readouterr().out


def test_same_seed_same_trials(tmp_path):
    args = ["registration", "--parts", "synthetic", "--trials", "1", "--solvers", "gnc_tls,ransac_1e3"]
    for name in ("a", "b"):
        assert main([*args, "--out", str(tmp_path / name)]) == 0

    def errors(name: str) -> list[tuple[str, str]]:
        with (tmp_path / name / "trials.csv").open() as handle:
            return [(row["rot_err_deg"], row["trans_err_m"]) for row in csv.DictReader(handle)]

    assert errors("a") == errors("b")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--parts", "real"], "needs --data"),
        (["--parts", "real", "--data", "/no/such/folder"], "no such folder"),
        (["--solvers", "nope"], "unknown or no solvers"),
        (["--trials", "0"], "--trials must be positive"),
        (["--trials", "x"], "invalid int value"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(tmp_path, capsys, args, message):
    assert main(["registration", "--out", str(tmp_path), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
