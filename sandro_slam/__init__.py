"""sandro_slam: loop closures between KISS-ICP keyframe submaps in a gtsam pose graph."""

from sandro_slam.config import SlamConfig
from sandro_slam.module import LoopClosure, LoopClosureModule
from sandro_slam.offline import OfflineSlam, SlamResult

__all__ = ["LoopClosure", "LoopClosureModule", "OfflineSlam", "SlamConfig", "SlamResult"]
