"""sandro_slam.refine: the second pass leaves exact poses where they are on a map of exact submaps."""

import numpy as np

from pipelines.simulation import simulate_sequence
from sandro_core.geometry import rotation_angle
from sandro_slam import SlamConfig
from sandro_slam.keyframes import Keyframe, submap_points
from sandro_slam.refine import refine_poses


def test_the_second_pass_keeps_exact_poses_on_a_map_of_exact_submaps():
    # The submaps hold one point per submap voxel (0.5 m): matched point to point, a scan's points are pulled by
    # that sampling (the scans' motion over 10 scans 5 cm off on a narrow-view car drive); Gaussian voxels are not.
    sequence = simulate_sequence(seed=0, laps=1, frames=60)
    config = SlamConfig().resolved()
    scans, truth = zip(*(sequence.deskewed(i) for i in range(len(sequence))))
    truth = np.array(truth)
    points = [scan.points for scan in scans]
    keyframes = [
        Keyframe(key, truth[first], first, 0.0, submap_points(truth[first], truth[first : first + 30],
                                                              points[first : first + 30], config.keyframes))
        for key, first in enumerate((0, 30))
    ]  # fmt: skip
    refined, _ = refine_poses(scans, truth, keyframes, {kf.key: kf.T_world_keyframe for kf in keyframes}, config)
    errors = np.linalg.inv(truth) @ refined
    translation = np.linalg.norm(errors[:, :3, 3], axis=1)
    rotation = np.degrees([rotation_angle(error[:3, :3]) for error in errors])
    assert translation.max() < 0.04  # 1.9 cm (7.3 cm point to point)
    assert rotation.max() < 0.1  # 0.03 deg (0.22 deg point to point)
