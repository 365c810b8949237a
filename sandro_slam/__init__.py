"""sandro_slam: loop closures between KISS-ICP keyframe submaps in a gtsam pose graph."""

from sandro_slam.config import SlamConfig
from sandro_slam.merge import MergeResult, merge_sessions
from sandro_slam.module import LoopCloser, LoopClosure, LoopClosureModule
from sandro_slam.odometry import GivenPoses
from sandro_slam.offline import OfflineSlam, SlamResult
from sandro_slam.robust_backend import check_loops
from sandro_slam.scan import Scan
from sandro_slam.session import Session

__all__ = [
    "GivenPoses",
    "LoopCloser",
    "LoopClosure",
    "LoopClosureModule",
    "MergeResult",
    "OfflineSlam",
    "Scan",
    "Session",
    "SlamConfig",
    "SlamResult",
    "check_loops",
    "merge_sessions",
]
