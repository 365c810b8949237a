"""sandro_slam: loop closures between KISS-ICP keyframe submaps in a gtsam pose graph (to come)."""
