"""The drifting odometry of the given-odometry runs."""

import numpy as np

from pipelines.simulation.drift import drifted


def test_drift_grows_with_the_distance_and_keeps_roll_and_pitch():
    poses = np.tile(np.eye(4), (101, 1, 1))
    poses[:, 0, 3] = np.arange(101.0)  # 100 m straight ahead
    np.testing.assert_array_equal(drifted(poses, 0.0), poses)
    odometry = drifted(poses, 0.005)
    error = np.linalg.norm(odometry[:, :3, 3] - poses[:, :3, 3], axis=1)
    assert error[0] == 0.0 and np.all(np.diff(error[1:]) > -1e-9)
    assert 0.2 < error[-1] < 0.5  # 0.5 % of 100 m in a direction that turns a third of a circle
    np.testing.assert_allclose(odometry[:, 2, :3], poses[:, 2, :3], atol=1e-12)  # the z axis stays upright
