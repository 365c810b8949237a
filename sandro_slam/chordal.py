"""Initial values of a pose graph that need none: the chordal relaxation of its rotations, then its translations.

Levenberg-Marquardt from the odometry's composed poses can end in a local minimum when the rotations have drifted
far, and creeps along the flat valleys of graphs that long odometry holds loosely; from the relaxation it reaches
the optimum in a few iterations (Carlone et al., "Initialization techniques for 3D SLAM", ICRA 2015). 3D: gtsam's
InitializePose3 (chordal rotations, then the translations' linear least squares); 2D: gtsam's LAGO, which takes
diagonal noise models only, so it gets each factor's covariance diagonal (the start only, not the solution), and
its spanning tree along consecutive keys where they are all joined, else from the graph (odometry with gaps).
"""

from __future__ import annotations

import gtsam
import numpy as np

from sandro_slam.factors import gaussian_noise

_POSE_FACTORS = {
    gtsam.BetweenFactorPose2: False,
    gtsam.PriorFactorPose2: False,
    gtsam.BetweenFactorPose3: True,
    gtsam.PriorFactorPose3: True,
}


def chordal_values(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> gtsam.Values | None:
    """Poses of every key of `graph` from its measurements alone, in the frame of its tightest prior (or, without
    one, of the first key's pose in `initial`). None when `graph` holds factors other than Pose2 or Pose3 between and
    prior factors, mixes 2D and 3D, or does not determine every pose (a part that no factor connects)."""
    kinds = {_POSE_FACTORS.get(type(graph.at(i))) for i in range(graph.size())}
    if len(kinds) != 1 or None in kinds:
        return None
    is3d = kinds.pop()
    anchored = _anchored(graph, initial, is3d)
    try:
        if is3d:
            values = gtsam.InitializePose3.initialize(anchored)
        else:
            values = gtsam.lago.initialize(_diagonal(anchored), useOdometricPath=_has_odometric_path(graph))
    except (RuntimeError, IndexError):  # gtsam: an indeterminate system, or LAGO's spanning tree misses a pose
        return None
    keys = set(graph.keyVector())
    if not keys <= set(values.keys()):
        return None
    out = gtsam.Values()
    for key in keys:
        out.insert(key, values.atPose3(key) if is3d else values.atPose2(key))
    if not np.isfinite(graph.error(out)):
        return None
    return out


def _has_odometric_path(graph: gtsam.NonlinearFactorGraph) -> bool:
    """Whether a between factor joins every key to the next (keys consecutive integers): LAGO's spanning tree is
    then that path, which it finds in linear time (its general search takes seconds on 10k poses)."""
    keys = sorted(graph.keyVector())
    steps = {tuple(sorted(graph.at(i).keys())) for i in range(graph.size()) if graph.at(i).size() == 2}
    return all((a, a + 1) in steps for a in keys[:-1]) if keys else False


def _anchored(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, is3d: bool) -> gtsam.NonlinearFactorGraph:
    """The between factors of `graph` and one prior: its tightest (largest information determinant), or, when it
    has none, one on its smallest key at that key's pose in `initial`. Loose priors (on the first pose of a
    further odometry chain, say) make the relaxation's linear systems indeterminate, and one fixes its frame."""
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
        tightest = prior_type(key, pose, gtsam.noiseModel.Isotropic.Sigma(6 if is3d else 3, 1e-3))
    anchored.add(tightest)
    return anchored


def _diagonal(graph: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
    """The 2D `graph` with each factor's noise model replaced by its covariance's diagonal (LAGO's input)."""
    out = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        sigmas = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(gaussian_noise(factor).covariance())))
        if isinstance(factor, gtsam.BetweenFactorPose2):
            out.add(gtsam.BetweenFactorPose2(factor.keys()[0], factor.keys()[1], factor.measured(), sigmas))
        else:
            out.add(gtsam.PriorFactorPose2(factor.keys()[0], factor.prior(), sigmas))
    return out
