"""Inter-session loops: keyframe pairs of two sessions registered like loop closures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sandro_slam.config import SlamConfig
from sandro_slam.loop_registration import SubmapDescription, register_submaps

Descriptions = list[dict[int, SubmapDescription]]  # per session index: the description of each keyframe's submap


@dataclass
class InterSessionLoop:
    """A verified loop between keyframes of two sessions: T_target_source maps the source keyframe's
    points into the target keyframe's frame."""

    target_session: int  # index into the sessions given
    target_key: int
    source_session: int
    source_key: int
    T_target_source: np.ndarray
    covariance: np.ndarray  # 6x6, gtsam order [rotation, translation], right perturbation
    inliers: int
    overlap: float
    found_by: str  # "place_recognition" or "guided"
    voted: bool = False  # agrees with the session transform its pair of sessions voted for (only these are used)
    conflict: float = float("nan")  # free-space conflict (`free_space`); nan: not tested
    weight: float = float("nan")  # robust back end's weight (below 0.5: rejected; nan: not in the graph)


def register_pairs(
    pairs: list[tuple[int, int, int, int]],
    descriptions: Descriptions,
    config: SlamConfig,
    found_by: str,
    map_function: Callable[[Callable, list[tuple]], list],
) -> list[InterSessionLoop]:
    """The verified loops among `pairs` (i, ki, j, kj): keyframe kj of session j registered onto keyframe ki of
    session i, the registrations run by `map_function`; in the order of `pairs`."""
    registered = map_function(
        register_submaps, [(descriptions[i][ki], descriptions[j][kj], config.registration) for i, ki, j, kj in pairs]
    )
    return [
        InterSessionLoop(i, ki, j, kj, pair.T_target_source, pair.covariance, pair.inliers, pair.overlap, found_by)
        for (i, ki, j, kj), pair in zip(pairs, registered)
        if pair.accepted
    ]
