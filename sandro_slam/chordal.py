"""Initial values of a pose graph that need none: the chordal relaxation of its rotations, then its translations.

Levenberg-Marquardt from the odometry's composed poses can end in a local minimum when the rotations have drifted
far, and creeps along the flat valleys of graphs that long odometry holds loosely; from the relaxation it reaches
the optimum in a few iterations (Carlone et al., "Initialization techniques for 3D SLAM", ICRA 2015). 3D: gtsam's
InitializePose3 (chordal rotations, then the translations' linear least squares); 2D: gtsam's LAGO, which takes
diagonal noise models only, so it gets each factor's covariance diagonal (the start only, not the solution), and
its spanning tree along the keys in their order (bridged where odometry chains leave gaps), else from the graph.
Each connected part of the graph is relaxed on its own and placed by its own prior; where the covariances leave a
rotation free, with every measurement weighed alike.
"""

from __future__ import annotations

from collections import deque

import gtsam
import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from sandro_slam.factors import gaussian_noise

ANCHOR_SIGMA = 1e-3  # [rad], [m] of the prior that fixes a part's frame at the origin
BRIDGE_SIGMA = 1e6  # [rad], [m] of the factors that join consecutive keys for LAGO's spanning tree only
_POSE_FACTORS = {
    gtsam.BetweenFactorPose2: False,
    gtsam.PriorFactorPose2: False,
    gtsam.BetweenFactorPose3: True,
    gtsam.PriorFactorPose3: True,
}


def chordal_values(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> gtsam.Values | None:
    """Poses of every key of `graph` from its measurements alone. Each connected part (sessions, or odometry chains
    that no factor joins) in the frame of its tightest prior, or, without one, of its smallest key's pose in
    `initial`. None when `graph` holds factors other than Pose2 or Pose3 between and prior factors, mixes 2D and 3D,
    or a part's relaxation is indeterminate."""
    kinds = {_POSE_FACTORS.get(type(graph.at(i))) for i in range(graph.size())}
    if len(kinds) != 1 or None in kinds:
        return None
    is3d = kinds.pop()
    out = gtsam.Values()
    for part in _parts(graph):
        anchored, anchor, pose = _anchored(part, initial, is3d)
        values = _relaxed(anchored, is3d)
        if values is None:  # covariances that leave a rotation free (a planar graph's roll and pitch, say)
            values = _relaxed(_reweighted(anchored, is3d, isotropic=True), is3d)
        if values is None:
            return None
        keys = set(part.keyVector())
        if not keys <= set(values.keys()):
            return None
        at = values.atPose3 if is3d else values.atPose2
        moved = pose.compose(at(anchor).inverse())  # the anchor onto its pose
        for key in keys:
            out.insert(key, moved.compose(at(key)))
    if not np.isfinite(graph.error(out)):
        return None
    return out


def _parts(graph: gtsam.NonlinearFactorGraph) -> list[gtsam.NonlinearFactorGraph]:
    """The connected parts of `graph`: the factors of each set of keys that its factors join."""
    keys = sorted(graph.keyVector())
    index = {key: n for n, key in enumerate(keys)}
    pairs = [[index[k] for k in graph.at(i).keys()] for i in range(graph.size()) if graph.at(i).size() == 2]
    rows, cols = np.array(pairs, dtype=int).reshape(-1, 2).T
    joined = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(keys), len(keys)))
    count, label = csgraph.connected_components(joined, directed=False)
    parts = [gtsam.NonlinearFactorGraph() for _ in range(count)]
    for i in range(graph.size()):
        parts[label[index[graph.at(i).keys()[0]]]].add(graph.at(i))
    return parts


def _with_odometric_path(graph: gtsam.NonlinearFactorGraph) -> tuple[gtsam.NonlinearFactorGraph, bool]:
    """(`graph`, whether LAGO may take its spanning tree along consecutive keys): found in linear time, where its
    general search took 0.3-0.5 s on 3500-4500 poses and 6.6 s on SE-Sync's ais2klinik (15115). Where the keys are
    consecutive integers but a pair of neighbours has no between factor (odometry chains that loops join), a copy
    with one, its measurement composed along a breadth-first tree of the measurements and its sigmas
    `BRIDGE_SIGMA`: it carries the tree's orientations across the gap and weighs nothing in the solution. False
    when the keys are not consecutive integers."""
    keys = sorted(graph.keyVector())
    if not keys or keys[-1] - keys[0] != len(keys) - 1:
        return graph, False
    steps: dict[int, list[tuple[int, gtsam.Pose2]]] = {}
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor.size() == 2:
            a, b = factor.keys()
            steps.setdefault(a, []).append((b, factor.measured()))
            steps.setdefault(b, []).append((a, factor.measured().inverse()))
    gaps = [a for a in keys[:-1] if all(b != a + 1 for b, _ in steps.get(a, []))]
    if not gaps:
        return graph, True
    poses = {keys[0]: gtsam.Pose2()}
    frontier = deque([keys[0]])
    while frontier:
        a = frontier.popleft()
        for b, step in steps.get(a, []):
            if b not in poses:
                poses[b] = poses[a].compose(step)
                frontier.append(b)
    if len(poses) < len(keys):  # not one part: LAGO's own search says so
        return graph, False
    bridged = gtsam.NonlinearFactorGraph(graph)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, BRIDGE_SIGMA)
    for a in gaps:
        bridged.add(gtsam.BetweenFactorPose2(a, a + 1, poses[a].between(poses[a + 1]), noise))
    return bridged, True


def _anchored(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, is3d: bool
) -> tuple[gtsam.NonlinearFactorGraph, int, gtsam.Pose2 | gtsam.Pose3]:
    """The between factors of `graph` with a tight prior at the origin on one key, the key and where it belongs: the
    pose of `graph`'s tightest prior (largest information determinant), or, when it has none, its smallest key's
    pose in `initial`. gtsam's relaxations solve in the frame of an origin (InitializePose3 finds no solution when a
    prior sits elsewhere), and loose priors (on the first pose of a further odometry chain, say) make their linear
    systems indeterminate."""
    prior_type = gtsam.PriorFactorPose3 if is3d else gtsam.PriorFactorPose2
    anchored = gtsam.NonlinearFactorGraph()
    tightest, best = None, -np.inf
    for i in range(graph.size()):
        factor = graph.at(i)
        if not isinstance(factor, prior_type):
            anchored.add(factor)
            continue
        logdet = np.linalg.slogdet(gaussian_noise(factor).information())[1]
        if logdet > best:
            tightest, best = factor, logdet
    if tightest is None:
        key = min(graph.keyVector())
        pose = initial.atPose3(key) if is3d else initial.atPose2(key)
    else:
        key, pose = tightest.keys()[0], tightest.prior()
    origin = gtsam.Pose3() if is3d else gtsam.Pose2()
    anchored.add(prior_type(key, origin, gtsam.noiseModel.Isotropic.Sigma(6 if is3d else 3, ANCHOR_SIGMA)))
    return anchored, key, pose


def _relaxed(graph: gtsam.NonlinearFactorGraph, is3d: bool) -> gtsam.Values | None:
    """gtsam's relaxation of an anchored `graph` (`_anchored`); None where it finds the system indeterminate."""
    try:
        if is3d:
            return gtsam.InitializePose3.initialize(graph)
        reweighted = _reweighted(graph, is3d)
        ranked, keys = _ranked(reweighted)
        values = gtsam.lago.initialize(*_with_odometric_path(ranked))
    except (RuntimeError, IndexError):  # gtsam: an indeterminate system, or LAGO's spanning tree misses a pose
        return None
    if ranked is reweighted:
        return values
    out = gtsam.Values()
    for number, key in enumerate(keys):
        out.insert(key, values.atPose2(number))
    return out


def _ranked(graph: gtsam.NonlinearFactorGraph) -> tuple[gtsam.NonlinearFactorGraph, list[int]]:
    """`graph` (2D between and prior factors) with its keys numbered 0, 1, ... in their order, and the keys by their
    number; `graph` itself where they are consecutive already. A graph the robust back end condensed
    (`chain_reduction`) holds its odometry between keys that follow each other with gaps in their numbers: numbered
    again, LAGO takes its tree along them (`_with_odometric_path`) instead of searching one."""
    keys = sorted(graph.keyVector())
    if not keys or keys[-1] - keys[0] == len(keys) - 1:
        return graph, keys
    number = {key: n for n, key in enumerate(keys)}
    out = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            a, b = factor.keys()
            out.add(gtsam.BetweenFactorPose2(number[a], number[b], factor.measured(), factor.noiseModel()))
        else:
            out.add(gtsam.PriorFactorPose2(number[factor.keys()[0]], factor.prior(), factor.noiseModel()))
    return out, keys


def _reweighted(graph: gtsam.NonlinearFactorGraph, is3d: bool, isotropic: bool = False) -> gtsam.NonlinearFactorGraph:
    """`graph` with each factor's noise model replaced by its covariance's diagonal (LAGO's input), or when
    `isotropic`, each between factor's by unit sigmas (a start that weighs every measurement alike)."""
    between = gtsam.BetweenFactorPose3 if is3d else gtsam.BetweenFactorPose2
    prior = gtsam.PriorFactorPose3 if is3d else gtsam.PriorFactorPose2
    out = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isotropic:
            noise = gtsam.noiseModel.Isotropic.Sigma(6 if is3d else 3, 1.0)
        else:
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(gaussian_noise(factor).covariance())))
        if isinstance(factor, between):
            out.add(between(factor.keys()[0], factor.keys()[1], factor.measured(), noise))
        else:
            out.add(factor if isotropic else prior(factor.keys()[0], factor.prior(), noise))
    return out
