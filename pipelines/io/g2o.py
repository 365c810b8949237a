"""Pose graphs as g2o files (VERTEX_SE3:QUAT / EDGE_SE3:QUAT), through gtsam's reader and writer."""

from __future__ import annotations

from pathlib import Path

import gtsam

from pipelines.io.atomic import atomic_path
from sandro_slam.factors import gaussian_noise


def write_g2o(path: str | Path, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> int:
    """Write the BetweenFactorPose3 factors of `graph` and the Pose3 `values` as g2o, atomically.

    gtsam.writeG2o refuses robust noise models: each is replaced by the Gaussian it wraps. Priors have no g2o
    edge and are left out (a reader anchors the first pose). Returns the number of edges written.
    """
    plain = gtsam.NonlinearFactorGraph()
    for index in range(graph.size()):
        factor = graph.at(index)
        if not isinstance(factor, gtsam.BetweenFactorPose3):
            continue
        plain.add(
            gtsam.BetweenFactorPose3(factor.keys()[0], factor.keys()[1], factor.measured(), gaussian_noise(factor))
        )
    with atomic_path(path) as tmp:
        gtsam.writeG2o(plain, values, str(tmp))
    return plain.size()


def read_g2o(path: str | Path) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Read a 3D g2o file: (BetweenFactorPose3 graph without prior, Pose3 values); ValueError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such g2o file: {path}")
    try:
        graph, values = gtsam.readG2o(str(path), True)
    except RuntimeError as error:
        raise ValueError(f"{path}: not a 3D g2o pose graph ({error})") from None
    if values.size() == 0:
        raise ValueError(f"{path}: no VERTEX_SE3:QUAT in it: not a 3D g2o pose graph")
    return graph, values
