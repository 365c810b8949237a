"""Summary, text tables and plot of `sandro-bench registration` results."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the backend
import numpy as np  # noqa: E402

Row = Mapping[str, object]
Key = tuple[str, str, str]  # (solver, case, outlier kind)
Panel = Callable[[plt.Axes], None]

SUMMARY_FIELDS = [
    "part", "solver", "case", "outlier_kind", "trials", "success_10deg_1m", "success_5deg_0.6m",
    "median_rot_err_deg", "median_trans_err_m", "median_time_s", "mean_n_corr", "mean_inlier_ratio", "errors",
]  # fmt: skip


def _column(rows: Sequence[Row], key: str) -> np.ndarray:
    return np.array([float(row[key]) for row in rows])


def _finite_median(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if len(finite) else math.nan


def summarize(rows: Sequence[Row]) -> list[dict[str, object]]:
    """One row per (part, solver, case, outlier kind), in order of appearance, plus for the real part
    one row per solver over all pairs (case 'all'). Success columns are rates in [0, 1]; error medians
    are over the trials in which the solver returned a transform."""
    groups: dict[tuple[str, str, str, str], list[Row]] = {}
    for row in rows:
        part, solver, kind = str(row["part"]), str(row["solver"]), str(row["outlier_kind"])
        groups.setdefault((part, solver, str(row["case"]), kind), []).append(row)
        if part == "real":
            groups.setdefault((part, solver, "all", kind), []).append(row)
    return [
        {
            "part": part,
            "solver": solver,
            "case": case,
            "outlier_kind": kind,
            "trials": len(group),
            "success_10deg_1m": float(np.mean(_column(group, "success_10deg_1m"))),
            "success_5deg_0.6m": float(np.mean(_column(group, "success_5deg_0.6m"))),
            "median_rot_err_deg": _finite_median(_column(group, "rot_err_deg")),
            "median_trans_err_m": _finite_median(_column(group, "trans_err_m")),
            "median_time_s": float(np.median(_column(group, "time_s"))),
            "mean_n_corr": float(np.mean(_column(group, "n_corr"))),
            "mean_inlier_ratio": float(np.mean(_column(group, "inlier_ratio"))),
            "errors": sum(1 for row in group if row["error"]),
        }  # fmt: skip
        for (part, solver, case, kind), group in groups.items()
    ]


def _by_key(summary: Sequence[Row], part: str) -> dict[Key, Row]:
    return {(str(r["solver"]), str(r["case"]), str(r["outlier_kind"])): r for r in summary if r["part"] == part}


def _unique(values: Iterable[object]) -> list[str]:
    return list(dict.fromkeys(str(value) for value in values))


def _pairs_then_all(real: dict[Key, Row]) -> list[str]:
    """The real pairs in order of appearance, then 'all'."""
    return [case for case in _unique(case for _, case, _ in real) if case != "all"] + ["all"]


def _median_time(rows: Sequence[Row], part: str, solver: str, case: str) -> float:
    """Median time [s] of one solver on one case ("all": every case), over every outlier kind."""
    times = [
        float(r["time_s"]) for r in rows if r["part"] == part and r["solver"] == solver and case in ("all", r["case"])
    ]
    return float(np.median(times))


def _table(title: str, solvers: list[str], columns: dict[str, str], cell: Callable[[str, str], str]) -> str:
    """A text table: one line per solver; `columns` maps a column key to its header."""
    lines = [["solver", *columns.values()]] + [[s, *(cell(s, key) for key in columns)] for s in solvers]
    widths = [max(len(line[i]) for line in lines) for i in range(len(lines[0]))]
    text = ["  ".join(t.rjust(w) if i else t.ljust(w) for i, (t, w) in enumerate(zip(line, widths))) for line in lines]
    return "\n".join(["", title, *text]) + "\n"


def _success(row: Row | None) -> str:
    if row is None:
        return "-"
    return f"{100 * float(row['success_10deg_1m']):.0f} ({100 * float(row['success_5deg_0.6m']):.0f})"


def _synthetic_tables(rows: Sequence[Row], summary: Sequence[Row], solvers: list[str]) -> str:
    synthetic = _by_key(summary, "synthetic")
    if not synthetic:
        return ""
    rates = {rate: f"{100 * float(rate):g}%" for rate in _unique(case for _, case, _ in synthetic)}
    text = ""
    for kind in _unique(kind for _, _, kind in synthetic):
        title = f"synthetic, {kind} outliers: success [%] at 10 deg/1 m (5 deg/0.6 m), by outlier rate"
        text += _table(title, solvers, rates, lambda s, rate, kind=kind: _success(synthetic.get((s, rate, kind))))
    title = "synthetic: median solver time [ms] (both outlier kinds), by outlier rate and over the sweep"
    columns = {**rates, "all": "all"}
    return text + _table(title, solvers, columns, lambda s, r: f"{1000 * _median_time(rows, 'synthetic', s, r):.1f}")


def _real_tables(summary: Sequence[Row], solvers: list[str], voxel_size: float, noise_bound: float) -> str:
    real = _by_key(summary, "real")
    if not real:
        return ""
    pairs = _pairs_then_all(real)

    def cell(solver: str, column: str) -> str:
        if column == "time":
            return f"{1000 * float(real[(solver, 'all', 'fpfh')]['median_time_s']):.1f} ms"
        return _success(real.get((solver, column, "fpfh")))

    title = (f"real pairs, FPFH at {voxel_size:g} m voxel, noise bound {noise_bound:g} m: success [%] at "
             "10 deg/1 m (5 deg/0.6 m); median solver time over all pairs")  # fmt: skip
    text = _table(title, solvers, {**{p: p for p in pairs}, "time": "median time"}, cell)
    stats = {p: real[(solvers[0], p, "fpfh")] for p in pairs if p != "all"}  # the same matches for every solver
    text += "FPFH matches (mean): " + ", ".join(f"{p} {float(r['mean_n_corr']):.0f}" for p, r in stats.items())
    ratios = ", ".join(f"{p} {100 * float(r['mean_inlier_ratio']):.1f}%" for p, r in stats.items())
    return text + f"\ninlier ratio (mean, residual <= {noise_bound:g} m): {ratios}\n"


def _scale_table(scale: Sequence[Row]) -> str:
    if not scale:
        return ""
    by_size = {(str(r["solver"]), str(r["n"])): r for r in scale}

    def cell(solver: str, n: str) -> str:
        row = by_size[(solver, n)]
        if row["status"] != "ok":
            return str(row["status"]).split(":")[0]
        wrong = "" if row["success_10deg_1m"] else " (wrong)"
        return f"{float(row['time_median_s']):.3g} s, {float(row['peak_memory_mb']):.0f} MB{wrong}"

    sizes = {str(n): str(n) for n in sorted({int(str(r["n"])) for r in scale})}
    title = (f"scale, {100 * float(str(scale[0]['outlier_rate'])):g}% uniform outliers: median time and peak "
             "memory above the set-up, by N ('wrong': beyond 10 deg / 1 m)")  # fmt: skip
    text = _table(title, _unique(r["solver"] for r in scale), sizes, cell)
    return text + "".join(f"  {r['solver']} N={r['n']}: {r['status']}\n" for r in scale if r["status"] != "ok")


def format_tables(
    rows: Sequence[Row],
    summary: Sequence[Row],
    scale: Sequence[Row],
    solvers: list[str],
    voxel_size: float,
    noise_bound: float,
) -> str:
    """Text tables: success rates [%] at 10 deg / 1 m (strict 5 deg / 0.6 m in brackets), median times,
    FPFH match statistics of the real pairs, and the scale results."""
    return (
        _synthetic_tables(rows, summary, solvers)
        + _real_tables(summary, solvers, voxel_size, noise_bound)
        + _scale_table(scale)
    )


def _synthetic_panels(
    rows: Sequence[Row], summary: Sequence[Row], solvers: list[str], colors: dict[str, object]
) -> list[Panel]:
    synthetic = _by_key(summary, "synthetic")
    if not synthetic:
        return []
    rates = _unique(case for _, case, _ in synthetic)
    x = np.arange(len(rates))
    axis = {"xticks": x, "xticklabels": [f"{100 * float(r):g}" for r in rates], "xlabel": "outlier rate [%]"}

    def success(kind: str) -> Panel:
        def draw(ax: plt.Axes) -> None:
            for s in solvers:
                y = [100 * float(synthetic[(s, r, kind)]["success_10deg_1m"]) for r in rates]
                ax.plot(x, y, "o-", color=colors[s])
            ax.set(title=f"synthetic, {kind} outliers", ylabel="success [%] (10 deg, 1 m)", ylim=(-5, 105), **axis)

        return draw

    def time(ax: plt.Axes) -> None:
        for s in solvers:
            ax.plot(x, [1000 * _median_time(rows, "synthetic", s, r) for r in rates], "o-", color=colors[s])
        ax.set(title="synthetic, median time (both kinds)", ylabel="time [ms]", yscale="log", **axis)

    return [success(kind) for kind in _unique(kind for _, _, kind in synthetic)] + [time]


def _real_panels(summary: Sequence[Row], solvers: list[str], colors: dict[str, object]) -> list[Panel]:
    real = _by_key(summary, "real")
    if not real:
        return []
    pairs = _pairs_then_all(real)

    def draw(ax: plt.Axes) -> None:
        width = 0.8 / len(solvers)
        for i, s in enumerate(solvers):
            offsets = np.arange(len(pairs)) + (i - (len(solvers) - 1) / 2) * width
            heights = [100 * float(real[(s, p, "fpfh")]["success_10deg_1m"]) for p in pairs]
            ax.bar(offsets, heights, width, color=colors[s])
        ax.set(title="real pairs, FPFH matches", ylabel="success [%] (10 deg, 1 m)", ylim=(0, 105))
        ax.set_xticks(np.arange(len(pairs)), pairs, rotation=30, ha="right")

    return [draw]


def _scale_panels(scale: Sequence[Row], solvers: list[str], colors: dict[str, object]) -> list[Panel]:
    def panel(column: str, label: str, yscale: str) -> Panel:
        def draw(ax: plt.Axes) -> None:
            for s in solvers:
                ok = [r for r in scale if r["solver"] == s and r["status"] == "ok"]
                ax.plot([int(str(r["n"])) for r in ok], [float(str(r[column])) for r in ok], "o-", color=colors[s])
            ax.set(title=f"scale, {label}", xlabel="correspondences N", ylabel=label, xscale="log", yscale=yscale)
            if yscale == "symlog":
                ax.set_ylim(0.0, 2.0 * max([float(str(r[column])) for r in scale if r["status"] == "ok"] + [1.0]))

        return draw

    if not scale:
        return []
    return [
        panel("time_median_s", "median time [s]", "log"),
        panel("peak_memory_mb", "peak memory [MB]", "symlog"),  # log above 2 MB, linear down to 0
    ]


def plot_results(
    rows: Sequence[Row], summary: Sequence[Row], scale: Sequence[Row], solvers: list[str], path: Path
) -> None:
    """PNG: synthetic success vs outlier rate (one panel per outlier kind) and median time; real success
    per pair; scale time and memory vs N. Panels of parts that did not run are left out."""
    colors = {s: plt.get_cmap("tab10")(i % 10) for i, s in enumerate(solvers)}
    panels = (
        _synthetic_panels(rows, summary, solvers, colors)
        + _real_panels(summary, solvers, colors)
        + _scale_panels(scale, solvers, colors)
    )
    ncols = min(3, max(1, len(panels)))
    nrows = max(1, math.ceil(len(panels) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.5 * ncols, 4.2 * nrows), squeeze=False)
    for ax, draw in zip(axes.flat, panels):
        draw(ax)
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    handles = [plt.Line2D([], [], color=colors[s], marker="o", label=s) for s in solvers]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(solvers), 7), frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
