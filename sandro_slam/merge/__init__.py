"""Joining sessions recorded at different times into one map, with no initial alignment.

1. Place recognition (`descriptor`: yaw-invariant ring keys of the submaps) proposes keyframe pairs across
   sessions.
2. Each pair is registered with the loop-closure registration (FPFH, SANDRO, ICP, verification).
3. Per pair of sessions, the verified loops vote on the session-to-session transform (`voting`); the pair is
   joined only when at least `min_loops` of them agree, and when the voted alignment passes the free-space
   test (`free_space`), the guard against aliasing: a place that looks like another one lets many loops agree
   on the wrong shift, but the other place differs in its small things (trees, poles, parked cars, a missing
   or taller building), which then land where the first session's rays passed freely.
4. Once aligned, keyframe pairs that now lie close together are registered too (guided search).
5. One gtsam graph (`graph`): every session's odometry and accepted loop factors, the inter-session loops, a
   prior on the first session's first keyframe; the robust back end with everything but the inter-session
   loops as known inliers. Pairs whose loops the back end rejects are split again; sessions left unconnected
   to the first are refused.
"""

from sandro_slam.merge.graph import MergeResult, session_key
from sandro_slam.merge.loops import InterSessionLoop
from sandro_slam.merge.pipeline import merge_sessions

__all__ = ["InterSessionLoop", "MergeResult", "merge_sessions", "session_key"]
