"""In-code ray-cast LiDAR sequences with ground truth, the test data of the SLAM benchmarks and tests.

`simulate_sequence(seed=0)` gives about 800 sweeps (two 400 m laps at 1 m spacing) of a 32-beam spinning
LiDAR driving through a city of repeated and mirror-symmetric blocks; see `sequence` for the conventions.
"""

from pipelines.simulation.sensor import PRESETS, Lidar, RosetteLidar, SpinningLidar, ZigzagLidar
from pipelines.simulation.sequence import SimulatedSequence, make_sequence, simulate_sequence
from pipelines.simulation.trajectory import PolylineRoute, Route, Trajectory
from pipelines.simulation.world import CityLayout, World, build_city

VERSION = 2  # bumped whenever the same arguments simulate different data (the demo's bag cache is keyed on it)

__all__ = [
    "PRESETS",
    "CityLayout",
    "Lidar",
    "PolylineRoute",
    "RosetteLidar",
    "Route",
    "SimulatedSequence",
    "SpinningLidar",
    "Trajectory",
    "VERSION",
    "World",
    "ZigzagLidar",
    "build_city",
    "make_sequence",
    "simulate_sequence",
]
