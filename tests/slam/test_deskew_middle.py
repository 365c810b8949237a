"""Scans deskewed into the sensor frame at the middle of their sweep (`odometry.deskew_to_middle`)."""

import gtsam
import numpy as np
from kiss_icp.preprocess import Preprocessor

from sandro_core.geometry import transform_points
from sandro_slam.odometry import deskew_to_middle, motion_power, sweep_middle

PERIOD = 0.1  # [s]
MOTION = gtsam.Pose3(gtsam.Rot3.Yaw(np.radians(6.0)), np.array([1.0, 0.1, 0.0])).matrix()  # T_start_end


def _sweep(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(world points (N, 3), the same in the sensor frame at each point's time, the times (N,) over PERIOD), the
    sensor starting at the identity and moving by MOTION over the sweep at constant velocity."""
    world = rng.uniform(-20.0, 20.0, size=(2000, 3))
    times = np.sort(rng.uniform(0.0, PERIOD, size=len(world)))
    sensed = np.array([transform_points(np.linalg.inv(motion_power(MOTION, t / PERIOD)), p[None])[0]
                       for p, t in zip(world, times)])  # fmt: skip
    return world, sensed, times


def _preprocessor(deskew: bool = True) -> Preprocessor:
    return Preprocessor(max_range=1e3, min_range=0.0, deskew=deskew, max_num_threads=1)


def test_points_land_in_the_sensor_frame_at_the_middle_of_the_sweep():
    world, sensed, times = _sweep(np.random.default_rng(0))
    span = motion_power(MOTION, (times.max() - times.min()) / PERIOD)  # the motion over the points' times
    deskewed = deskew_to_middle(_preprocessor(), sensed, times, span, deskew=True)
    T_world_middle = motion_power(MOTION, sweep_middle(times) / PERIOD)
    np.testing.assert_allclose(deskewed, transform_points(np.linalg.inv(T_world_middle), world), atol=1e-6)


def test_a_wrong_velocity_leaves_the_cloud_in_place_about_the_middle():
    # Deskewed with a motion 10 % too long, the cloud about the sweep's end moves by about half the error; about
    # its middle the points before and after it move in opposite directions.
    world, sensed, times = _sweep(np.random.default_rng(1))
    span = motion_power(MOTION, (times.max() - times.min()) / PERIOD)
    wrong = motion_power(span, 1.1)
    preprocessor = _preprocessor()
    at_middle = deskew_to_middle(preprocessor, sensed, times, wrong, deskew=True)
    true_middle = deskew_to_middle(preprocessor, sensed, times, span, deskew=True)
    at_end = preprocessor.preprocess(sensed, times, wrong)
    true_end = preprocessor.preprocess(sensed, times, span)
    shift_middle = np.linalg.norm((at_middle - true_middle).mean(axis=0))
    shift_end = np.linalg.norm((at_end - true_end).mean(axis=0))
    assert shift_end > 0.04  # half of the 0.1 m error
    assert shift_middle < 0.1 * shift_end


def test_scans_without_times_stay_as_they_are():
    _, sensed, _ = _sweep(np.random.default_rng(2))
    np.testing.assert_array_equal(deskew_to_middle(_preprocessor(), sensed, np.zeros(0), MOTION, deskew=True), sensed)
    times = np.linspace(0.0, PERIOD, len(sensed))
    off = _preprocessor(deskew=False)  # deskewing off in the configuration: KISS-ICP's and ours alike
    np.testing.assert_array_equal(deskew_to_middle(off, sensed, times, MOTION, deskew=False), sensed)
