"""Figures of the command-line tools and benchmarks: top views of trajectories and loops, errors over time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the backend
import numpy as np  # noqa: E402

from pipelines.evaluation import align_se3, ate  # noqa: E402
from pipelines.io.atomic import atomic_path  # noqa: E402
from sandro_slam import MergeResult, SlamResult  # noqa: E402


def save_figure(fig: plt.Figure, path: Path, dpi: int = 120) -> None:
    """Write `fig` to `path` (the format from its suffix) atomically, and close it."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)


def plot_slam(path: Path, result: SlamResult, truth: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """A top view of the trajectory before (odometry) and after loop closure, with accepted (green) and rejected
    (red, dashed) loops between the optimised keyframe positions; the ground truth too when given as
    (mask of the frames it covers, poses at them), SE3-aligned to the optimised trajectory's matched frames, and
    then the position error over time beside it."""
    if truth is None:
        fig, ax = plt.subplots(figsize=(9, 8))
    else:
        fig, (ax, errors) = plt.subplots(1, 2, figsize=(15, 7), gridspec_kw={"width_ratios": [3, 2]})
        mask, poses = truth
        gt = align_se3(poses, result.poses[mask]) @ poses
        ax.plot(gt[:, 0, 3], gt[:, 1, 3], color="0.6", lw=3, alpha=0.5, label="ground truth")
        draw_errors(
            errors,
            result.timestamps[mask] - result.timestamps[0],
            poses,
            {"odometry": result.odometry_poses[mask], "after loop closure": result.poses[mask]},
            colors=["tab:orange", "tab:blue"],
        )
    ax.plot(
        result.odometry_poses[:, 0, 3],
        result.odometry_poses[:, 1, 3],
        color="tab:orange",
        lw=1,
        label="odometry (KISS-ICP)",
    )
    ax.plot(result.poses[:, 0, 3], result.poses[:, 1, 3], color="tab:blue", lw=1.2, label="after loop closure")
    for accepted, style in ((True, dict(color="tab:green", lw=0.8)), (False, dict(color="tab:red", lw=1, ls="--"))):
        label = "accepted loop" if accepted else "rejected loop"
        for loop in (lp for lp in result.loops if (lp.weight >= 0.5) == accepted):
            a, b = (result.keyframe_poses[k][:3, 3] for k in (loop.source_key, loop.target_key))
            ax.plot([a[0], b[0]], [a[1], b[1]], label=label, **style)
            label = None
    _top_view(ax)
    accepted = sum(loop.weight >= 0.5 for loop in result.loops)
    ax.set_title(
        f"{len(result.timestamps)} frames, {len(result.keyframes)} keyframes, "
        f"{accepted} loops accepted, {len(result.loops) - accepted} rejected"
    )
    ax.legend(loc="best")
    save_figure(fig, path)


def plot_trajectories(
    path: Path, times: np.ndarray, truth: np.ndarray, estimates: dict[str, np.ndarray], title: str
) -> None:
    """Top view of estimated trajectories, each SE3-aligned to the ground truth `truth` (all (F, 4, 4) at
    `times` [s]), and their position errors over time."""
    fig, (ax, errors) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [3, 2]})
    ax.plot(truth[:, 0, 3], truth[:, 1, 3], label="ground truth", color="0.6", lw=2.5, alpha=0.5)
    for name, poses in estimates.items():  # colours C0, C1, ... as in the error panel
        aligned = align_se3(poses, truth) @ poses
        ax.plot(aligned[:, 0, 3], aligned[:, 1, 3], label=name, lw=1.2, alpha=0.9)
    draw_errors(errors, times - times[0], truth, estimates)
    _top_view(ax)
    ax.set_title(title)
    ax.legend()
    save_figure(fig, path)


def draw_errors(
    ax: plt.Axes,
    times: np.ndarray,
    truth: np.ndarray,
    estimates: dict[str, np.ndarray],
    colors: list[str] | None = None,
) -> None:
    """Position error [m] over `times` [s] of each (F, 4, 4) estimate after an SE3 alignment to `truth`,
    labelled with its ATE."""
    for index, (name, poses) in enumerate(estimates.items()):
        aligned = align_se3(poses, truth) @ poses
        error = np.linalg.norm(aligned[:, :3, 3] - truth[:, :3, 3], axis=1)
        ax.plot(
            times,
            error,
            lw=1,
            color=None if colors is None else colors[index],
            label=f"{name} (ATE {ate(poses, truth):.3f} m)",
        )
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error after SE3 alignment [m]")
    ax.legend(loc="upper left")


def plot_suite(path: Path, rows: list[dict]) -> None:
    """The evaluation suite at a glance: ATE [m] per sequence and method (log scale; rows hold `ate_<method>`),
    and frames/s per sequence of the pipelines (`fps_<pipeline>`)."""
    names = [row["sequence"] for row in rows]
    methods = [key[4:] for key in dict.fromkeys(k for row in rows for k in row) if key.startswith("ate_")]
    pipelines = [key[4:] for key in dict.fromkeys(k for row in rows for k in row) if key.startswith("fps_")]
    x = np.arange(len(rows))
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(max(10.0, 0.9 * len(rows) + 4.0), 9), sharex=True)
    for axis, keys, prefix, label in ((top, methods, "ate_", "ATE [m]"), (bottom, pipelines, "fps_", "frames/s")):
        width = 0.8 / max(1, len(keys))
        for k, key in enumerate(keys):
            values = [row.get(prefix + key, np.nan) for row in rows]
            axis.bar(x + (k - 0.5 * (len(keys) - 1)) * width, values, width, label=key.replace("_", " "))
        axis.set_ylabel(label)
        axis.legend(loc="best", fontsize=8)
        axis.grid(axis="y", alpha=0.3)
    top.set_yscale("log")
    bottom.set_xticks(x, names, rotation=40, ha="right")
    save_figure(fig, path)


def plot_merges(path: Path, merges: dict[str, MergeResult]) -> None:
    """One panel per merge (titled by its key): `draw_merge`."""
    fig, axes = plt.subplots(1, len(merges), figsize=(8.5 * len(merges), 8), squeeze=False)
    for ax, (title, result) in zip(axes[0], merges.items()):
        draw_merge(ax, result, title)
    save_figure(fig, path, dpi=110)


def draw_merge(ax: plt.Axes, result: MergeResult, title: str) -> None:
    """Top view of every joined session's merged trajectory and the inter-session loops in the graph (kept:
    solid black, rejected by the back end: dotted red)."""
    for name in result.joined:
        poses = result.frame_poses[name]
        ax.plot(poses[:, 0, 3], poses[:, 1, 3], lw=1.2, label=name)
    for loop in result.loops:
        if np.isnan(loop.weight):
            continue
        a = result.keyframe_poses[result.names[loop.target_session]][loop.target_key][:2, 3]
        b = result.keyframe_poses[result.names[loop.source_session]][loop.source_key][:2, 3]
        kept = loop.weight >= 0.5
        ax.plot([a[0], b[0]], [a[1], b[1]], "k-" if kept else "r:", lw=0.8 if kept else 1.0)
    ax.plot([], [], "k-", label="inter-session loop")
    ax.plot([], [], "r:", label="rejected by the back end")
    _top_view(ax)
    ax.legend()
    ax.set_title(title)


def _top_view(ax: plt.Axes) -> None:
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
