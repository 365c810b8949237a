"""Which loops of a pose graph agree with their neighbours: pairwise consistency over short odometry chains.

Two loops whose endpoints lie within `MAX_WINDOW` poses of each other along the odometry chains close a cycle: loop i,
the chain from its target to loop j's target, loop j backwards, the chain from j's source back to i's source. Real
loops close it up to their noise and the little drift of the short chains; a wrong loop does not. A loop is
supported when most of its nearest neighbours agree with it. What "agrees" means comes from the graph itself: an
error below `AGREE_FACTOR` times the median error of the closest pairs tested (mostly pairs of real loops, since
wrong loops rarely have close neighbours), grown with the separation, in metres and radians apart, so that
covariances not to scale do not matter.

The support only seeds the robust back end (`robust_backend`): loops without neighbours are decided there.
"""

from __future__ import annotations

from collections import deque

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from sandro_core.geometry import rotation_angle

MAX_WINDOW = 6  # poses along a chain between neighbouring loops' ends: wider windows add drift that hides wrong loops
AGREE_FACTOR = 5.0  # an agreeing pair's error is below this many times the median error of the pairs tested
MIN_PAIRS = 10  # pairs at the smallest separation needed for a median to judge them by
MIN_AGREEING = 2  # neighbours that agree with a supported loop: two wrong loops can agree with each other by chance


def supported_loops(graph: gtsam.NonlinearFactorGraph, known_inliers: list[int]) -> np.ndarray:
    """(L,) bool per loop, in factor order: supported by most of its neighbours. Loops are the factors not in
    `known_inliers`; the odometry chains are the known-inlier BetweenFactorPose2/3. A loop of another factor type
    is never supported."""
    known = set(known_inliers)
    loops = [i for i in range(graph.size()) if i not in known]
    supported = np.zeros(len(loops), dtype=bool)
    chains = _Chains(graph, known_inliers)
    ends, measured = [], []
    for position, index in enumerate(loops):
        factor = graph.at(index)
        ends_of = chains.ends(factor)
        if ends_of is None:
            continue
        (ca, oa, ra), (cb, ob, rb) = ends_of
        pose = factor.measured()
        if (ca, oa) > (cb, ob):  # the same direction for every loop: the lower end first
            (ca, oa, ra), (cb, ob, rb), pose = (cb, ob, rb), (ca, oa, ra), pose.inverse()
        ends.append((position, ca, oa, cb, ob, ra, rb))
        measured.append(_matrix(pose))
    if len(ends) < 2:
        return supported
    ends_arr = np.array(ends)
    measured_arr = np.array(measured)
    # Neighbours: the same pair of chains, both ends within MAX_WINDOW poses (chain ids spread beyond that).
    spread = 10.0 * MAX_WINDOW + 10.0
    points = ends_arr[:, [1, 2, 3, 4]].astype(float) * [spread, 1.0, spread, 1.0]
    pairs = cKDTree(points).query_pairs(MAX_WINDOW, p=np.inf, output_type="ndarray")
    if len(pairs) == 0:
        return supported
    i, j = pairs[:, 0], pairs[:, 1]
    separation = np.maximum(np.abs(ends_arr[i, 2] - ends_arr[j, 2]), np.abs(ends_arr[i, 4] - ends_arr[j, 4]))
    P = chains.poses
    a, b = ends_arr[:, 5], ends_arr[:, 6]
    # The cycle: loop i^-1, chain a_i -> a_j, loop j, chain b_j -> b_i; the identity for loops that agree. Per
    # loop first (X = loop^-1 P_a^-1, Y = P_a loop P_b^-1), then two products per pair: X_i Y_j P_b_i.
    P_a_loop = P[a] @ measured_arr
    X = _rigid_inverse(P_a_loop)
    Y = P_a_loop @ _rigid_inverse(P[b])
    cycle = X[i] @ Y[j] @ P[b[i]]
    translation = np.linalg.norm(cycle[:, :3, 3], axis=1)
    rotation = rotation_angle(cycle[:, :3, :3])
    # Each loop is judged by its nearest neighbours (the smallest separation at which it has any).
    nearest = np.full(len(ends), MAX_WINDOW + 1)
    np.minimum.at(nearest, i, separation)
    np.minimum.at(nearest, j, separation)
    # The error of agreeing pairs grows with their separation as the drift of the chains between them does,
    # about as its square root; its scale comes from the closest pairs, which real loops dominate most.
    levels, counts = np.unique(separation, return_counts=True)
    if counts.max() < MIN_PAIRS:
        return supported
    base = int(levels[np.argmax(counts >= MIN_PAIRS)])
    at = separation == base
    growth = np.sqrt(np.maximum(separation, 1) / max(base, 1))
    scale_t = max(float(np.median(translation[at])), 1e-9) * growth
    scale_r = max(float(np.median(rotation[at])), 1e-12) * growth
    agree = np.maximum(translation / scale_t, rotation / scale_r) <= AGREE_FACTOR
    used = (separation == nearest[i]) | (separation == nearest[j])
    agreeing = np.zeros(len(ends), dtype=int)
    tested = np.zeros(len(ends), dtype=int)
    for side in (i, j):
        mine = used & (separation == nearest[side])
        np.add.at(agreeing, side[mine & agree], 1)
        np.add.at(tested, side[mine], 1)
    backed = (agreeing >= MIN_AGREEING) & (2 * agreeing >= tested)
    supported[ends_arr[backed, 0]] = True
    return supported


class _Chains:
    """The odometry chains of a graph (connected components of its known-inlier between factors): per pose, its
    chain id, its position along the chain (its depth from the chain's smallest key) and its row in `poses`, the
    poses composed along the chain from there (4x4, 2D poses lifted)."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, known_inliers: list[int]):
        neighbours: dict[int, list[tuple[int, np.ndarray]]] = {}
        for index in known_inliers:
            factor = graph.at(index)
            if not _is_between(factor):
                continue
            a, b = factor.keys()
            step = factor.measured()
            neighbours.setdefault(a, []).append((b, _matrix(step)))
            neighbours.setdefault(b, []).append((a, _matrix(step.inverse())))
        self._where: dict[int, tuple[int, int, int]] = {}
        poses = []
        chain = -1
        for root in sorted(neighbours):
            if root in self._where:
                continue
            chain += 1
            self._where[root] = (chain, 0, len(poses))
            poses.append(np.eye(4))
            frontier = deque([root])
            while frontier:
                key = frontier.popleft()
                _, depth, row = self._where[key]
                for other, T in neighbours[key]:
                    if other not in self._where:
                        self._where[other] = (chain, depth + 1, len(poses))
                        poses.append(poses[row] @ T)
                        frontier.append(other)
        self.poses = np.array(poses) if poses else np.empty((0, 4, 4))

    def ends(self, factor: gtsam.NonlinearFactor) -> tuple[tuple[int, int, int], tuple[int, int, int]] | None:
        """((chain, position, row) of each end) of a between factor on chain poses; None otherwise."""
        if not _is_between(factor):
            return None
        a, b = factor.keys()
        if a not in self._where or b not in self._where:
            return None
        return self._where[a], self._where[b]


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    """The inverses of a stack (..., 4, 4) of rigid transforms."""
    inverse = np.zeros_like(T)
    R_T = np.swapaxes(T[..., :3, :3], -1, -2)
    inverse[..., :3, :3] = R_T
    inverse[..., :3, 3] = -(R_T @ T[..., :3, 3:])[..., 0]
    inverse[..., 3, 3] = 1.0
    return inverse


def _is_between(factor: gtsam.NonlinearFactor) -> bool:
    return isinstance(factor, (gtsam.BetweenFactorPose3, gtsam.BetweenFactorPose2))


def _matrix(pose: gtsam.Pose3 | gtsam.Pose2) -> np.ndarray:
    """4x4 of a Pose3, or of a Pose2 lifted to the plane z = 0."""
    if isinstance(pose, gtsam.Pose3):
        return pose.matrix()
    T = np.eye(4)
    M = pose.matrix()
    T[:2, :2], T[:2, 3] = M[:2, :2], M[:2, 2]
    return T
