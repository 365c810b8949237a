"""The damaged-input part of `sandro-bench slam`: the drive as a recording that lost messages, holds cut sweeps and
repeats some.

Real bags lose LiDAR messages (a recorder that cannot keep up, a network link), drivers publish partial sweeps (the
first one after start-up, lost packets), and merged bags can hold a message twice. Here every LOST_EVERY-th sweep
of the drive is dropped; of the sweeps left the first and every CUT_EVERY-th keep only their first CUT_POINTS
points, and every REPEATED_EVERY-th (from the 20th) is recorded twice. Measured: the frames sandro-slam skipped,
and the ATE of its odometry and of its result, against those of the whole drive.
"""

from __future__ import annotations

from pipelines.evaluation import ate
from pipelines.simulation import SimulatedSequence
from sandro_slam import OfflineSlam, Scan, SlamConfig

LOST_EVERY = 10  # sweeps; the 6th, 16th, ... are lost
CUT_EVERY = 25  # of the sweeps left; the 1st, 26th, ... are cut
CUT_POINTS = 20
REPEATED_EVERY = 40  # of the sweeps left; the 20th, 60th, ... are recorded twice


def damaged_frames(frames: list[Scan]) -> tuple[list[Scan], int, int, int]:
    """(the frames damaged as the module docstring says, how many lost, how many cut, how many repeated)."""
    kept = [frame for index, frame in enumerate(frames) if index % LOST_EVERY != LOST_EVERY // 2]
    damaged = []
    for index, f in enumerate(kept):
        damaged.append(Scan(f.timestamp, f.points[:CUT_POINTS], f.times[:CUT_POINTS]) if index % CUT_EVERY == 0 else f)
        if index % REPEATED_EVERY == REPEATED_EVERY // 2:
            damaged.append(damaged[-1])
    cut, repeated = len(range(0, len(kept), CUT_EVERY)), len(range(REPEATED_EVERY // 2, len(kept), REPEATED_EVERY))
    return damaged, len(frames) - len(kept), cut, repeated


def damaged_input_experiment(sequence: SimulatedSequence, frames: list[Scan], config: SlamConfig) -> dict[str, float]:
    """Metrics `damaged_*`: frames lost, cut, repeated and skipped; ATE of the odometry and of sandro-slam; loops
    verified."""
    damaged, lost, cut, repeated = damaged_frames(frames)
    print(f"sandro-slam with {lost} sweeps lost, {cut} cut to {CUT_POINTS} points, {repeated} twice ...", flush=True)
    result = OfflineSlam(config).run(damaged, progress=True)
    truth = sequence.poses_at(result.timestamps)
    return {
        "damaged_frames_lost": lost,
        "damaged_frames_cut": cut,
        "damaged_frames_repeated": repeated,
        "damaged_frames_skipped": len(result.skipped_frames),
        "damaged_ate_odometry": ate(result.odometry_poses, truth),
        "damaged_ate_sandro_slam": ate(result.poses, truth),
        "damaged_loops_verified": len(result.loops),
        "damaged_loops_rejected": len(result.rejected_loops),
    }
