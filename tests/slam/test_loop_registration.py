"""sandro_slam.loop_registration: a submap description survives pickling (to worker processes) unchanged."""

import pickle

import numpy as np

from sandro_slam.config import SlamConfig
from sandro_slam.loop_registration import describe_submap, register_submaps


def test_a_pickled_description_registers_exactly_as_the_original(drive):
    truth, _, scans = drive
    config = SlamConfig().resolved().registration
    target, source = describe_submap(scans[0], config), describe_submap(scans[1], config)
    copies = [pickle.loads(pickle.dumps(d)) for d in (target, source)]
    for original, copy in zip((target, source), copies):
        np.testing.assert_array_equal(copy.keypoints, original.keypoints)
        np.testing.assert_array_equal(np.asarray(copy.cloud.normals), np.asarray(original.cloud.normals))
        np.testing.assert_array_equal(np.asarray(copy.icp_points.points), np.asarray(original.icp_points.points))
    first, again = register_submaps(target, source, config), register_submaps(*copies, config)
    assert first.accepted == again.accepted
    np.testing.assert_array_equal(again.T_target_source, first.T_target_source)
