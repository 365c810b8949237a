"""OfflineSlam: KISS-ICP odometry, keyframes, loop closures and the final optimisation over a stream of scans."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from sandro_slam.background import BackgroundLoopClosure, usable_cores
from sandro_slam.config import SlamConfig
from sandro_slam.frontend import Frontend
from sandro_slam.keyframes import Keyframe
from sandro_slam.module import LoopClosure, LoopClosureModule
from sandro_slam.odometry import GivenPoses
from sandro_slam.refine import rebuilt_keyframes, refine_poses, reoptimized
from sandro_slam.scan import MIN_VOXELS, VOXEL_COUNT_SCANS, Scan, SparseScans, as_scan, occupied_voxels
from sandro_slam.scene_scale import SCANS, scene_scale
from sandro_slam.sweep_times import TEST_SCANS, Rotation, detected_rotation, sweep_period, with_azimuth_times
from sandro_slam.timing import Stopwatch


@dataclass
class SlamResult:
    """Poses are T_world_sensor (4x4) per processed frame; the world frame is the first scan's."""

    timestamps: np.ndarray  # (F,) [s] the time each pose refers to: stamp + the middle of the first and last
    # per-point time (`odometry.deskew_to_middle`), the stamp itself for frames without per-point times
    poses: np.ndarray  # (F, 4, 4) optimised: every scan moved with its keyframe
    odometry_poses: np.ndarray  # (F, 4, 4) the odometry alone: KISS-ICP's, its first scans re-registered
    # (reregister_start), or the poses given
    keyframes: list[Keyframe]
    keyframe_of_frame: np.ndarray  # (F,) key of the keyframe each frame belongs to
    T_keyframe_frame: np.ndarray  # (F, 4, 4) each frame's pose relative to its keyframe: the odometry's (after
    # `OfflineSlam.refine`: the refined scans')
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values  # initial keyframe poses (odometry)
    keyframe_poses: dict[int, np.ndarray]  # optimised T_world_keyframe
    loops: list[LoopClosure]  # verified loops; `weight` < 0.5 means the back end rejected them
    rejected_loops: list[LoopClosure]
    skipped_frames: list[int]  # input frames without any finite point, with too few points (`SparseScans`), that
    # repeat the frame before (stamp and points), or without a given odometry pose
    odometry_noise_scale: float  # on the odometry covariances in the final optimisation (1: as configured)
    config: SlamConfig  # the configuration used, every length resolved (`SlamConfig.resolved`)
    timings: dict[str, float] = field(default_factory=dict)  # wall seconds: odometry, loop_closure (in this
    # process), optimization (with `loops.in_background`: also the wait for the worker), total; the worker's
    # loop_closure_worker_cpu (CPU seconds) when it ran; sweep_test where `sweep_times: auto` judged scans without
    # per-point times (`detected_rotation`)

    def frame_poses(self, keyframe_poses: dict[int, np.ndarray]) -> np.ndarray:
        """(F, 4, 4) T_world_sensor of every frame, each moved rigidly with its keyframe to `keyframe_poses`."""
        return np.stack([keyframe_poses[int(key)] for key in self.keyframe_of_frame]) @ self.T_keyframe_frame


class OfflineSlam:
    """Runs the whole pipeline over scans; `module` is the LoopClosureModule it drives (made by `run` when the
    configuration leaves the scale to be measured), so that a caller can add factors and re-optimise."""

    def __init__(self, config: SlamConfig | None = None):
        self.config = config or SlamConfig()
        self.module = LoopClosureModule(self.config) if self.config.scale is not None else None

    def run(
        self, frames: Iterable[Scan | Sequence], progress: bool = False, odometry: GivenPoses | None = None
    ) -> SlamResult:
        """Process scans in order: `Scan`s or tuples (timestamp, points[, per-point times]), points in the sensor
        frame. Frames without a finite point, occupying too few odometry voxels (`SparseScans`: fewer than 100, or
        than a tenth of the frames before), or repeating the frame before (its stamp and points: a message
        recorded twice) are skipped (`skipped_frames`); other non-finite points are dropped.

        `odometry`: the poses of another front end instead of KISS-ICP (scans with per-point times deskewed along
        timed poses, `GivenPoses.deskew`; others taken as deskewed); frames it has no pose for are skipped too.

        With `loops.in_background` and more than one core, `module` works in a worker process beside the
        odometry (`BackgroundLoopClosure`) and is replaced by what the worker returns, with the same content.
        """
        start = time.perf_counter()
        scans = (
            (index, _finite(as_scan(frame, index))) for index, frame in enumerate(_with_progress(frames, progress))
        )
        unset_scale = self.config.scale is None  # a scale set is used as it is
        head = _first_scans(scans) if unset_scale or _needs_head(self.config, odometry) else []
        if head and unset_scale:
            data = self.config.odometry.data
            scale = scene_scale([scan.points for _, scan in head if len(scan.points)], data.min_range, data.max_range)
            self.module = LoopClosureModule(self.config.resolved(scale))
        elif self.module is None:
            self.module = LoopClosureModule(self.config.resolved())  # the scale set, or 1 without any scan
        config = self.module.config
        sweep_test = None  # seconds `detected_rotation` took, where it ran
        if odometry is not None:
            config.sweep_times = "none"  # a given odometry takes scans without times as deskewed (`GivenPoses`)
        elif config.sweep_times == "auto":
            head, sweep_test = _told_sweep_times(config, head, scans)
        rotation = _sweep_rotation(config)
        if rotation is not None:
            period = _head_period(head)
            head = [(index, with_azimuth_times(scan, period, rotation)) for index, scan in head]
            scans = ((index, with_azimuth_times(scan, period, rotation)) for index, scan in scans)
        policy = config.graph.estimate_odometry_noise
        self.module.estimate_odometry_noise = policy == "always" or (
            policy == "given_odometry" and odometry is not None
        )
        in_background = config.loops.in_background and usable_cores() > 1
        with BackgroundLoopClosure(self.module) if in_background else nullcontext() as background:
            stopwatch = Stopwatch("odometry", "loop_closure", "optimization")
            frontend = Frontend(config, background or self.module, stopwatch, odometry)
            skipped, added = [], []  # indices of the input frames
            kiss = config.odometry
            grid = (kiss.mapping.voxel_size, kiss.data.min_range, kiss.data.max_range)
            head_counts = {  # of the first scans, read ahead: they seed SparseScans and are judged by it
                index: occupied_voxels(scan.points, *grid)
                for index, scan in head[:VOXEL_COUNT_SCANS]
                if len(scan.points)
            }
            sparse = SparseScans(head_counts.values())
            previous = None
            for index, scan in itertools.chain(head, scans):
                repeated, previous = _same_sweep(scan, previous), scan
                if repeated:  # a message recorded twice: KISS-ICP would take it for a stop
                    skipped.append(index)
                elif sparse(head_counts.pop(index) if index in head_counts else occupied_voxels(scan.points, *grid)):
                    skipped.append(index)
                    frontend.skip(scan.timestamp)
                else:
                    added.append(index)
                    frontend.add(scan)
            if skipped and not added:
                raise ValueError(
                    f"no frame to process: all {len(skipped)} hold fewer than {MIN_VOXELS} occupied {grid[0]:g} m "
                    f"voxels within {grid[1]:g}-{grid[2]:g} m of the sensor (are the points in the sensor frame?)"
                )
            frontend.finish()
            skipped = sorted(skipped + [added[i] for i in frontend.unmatched])
            timings = stopwatch.seconds
            if sweep_test is not None:
                timings["sweep_test"] = sweep_test
            with stopwatch("optimization"):
                if background is None:
                    keyframe_poses = self.module.optimize()
                else:
                    self.module, keyframe_poses, timings["loop_closure_worker_cpu"] = background.finish()
        timings["total"] = time.perf_counter() - start
        return self._result(frontend, keyframe_poses, skipped, timings)

    def refine(self, frames: Iterable[Scan | Sequence], result: SlamResult, progress: bool = False) -> SlamResult:
        """The second pass (`refine`): `result` with every scan refined against the map of the loop-corrected
        submaps, the keyframe submaps made again from the refined scans, the loops the first pass kept measured
        again on them (ICP), the graph optimised again. `frames` are those `run` made `result` from, read again
        (skipped ones included). `odometry_poses` stay the first pass's; adds timings["refine"] (and to "total")."""
        start = time.perf_counter()
        skipped = set(result.skipped_frames)
        used = (
            scan
            for index, frame in enumerate(_with_progress(frames, progress, "refine"))
            if index not in skipped and len((scan := _finite(as_scan(frame, index))).points)
        )
        config = result.config
        rotation = _sweep_rotation(config)
        if rotation is not None:  # the times the first pass gave the scans
            head = list(itertools.islice(used, SCANS))
            period = sweep_period([scan.timestamp for scan in head])
            used = (with_azimuth_times(scan, period, rotation) for scan in itertools.chain(head, used))
        scan_poses, scans = refine_poses(
            itertools.islice(used, len(result.poses)), result.poses, result.keyframes, result.keyframe_poses, config
        )
        keyframes = rebuilt_keyframes(result.keyframes, result.keyframe_of_frame, scan_poses, scans, config.keyframes)
        del scans
        graph, loops, keyframe_poses = reoptimized(
            keyframes, result.loops, config, estimate_odometry_noise=result.odometry_noise_scale != 1.0
        )
        seconds = time.perf_counter() - start
        refined = replace(
            result,
            keyframes=keyframes,
            T_keyframe_frame=_relative_to_keyframes(keyframes, result.keyframe_of_frame, scan_poses),
            graph=graph.graph,
            values=graph.values,
            keyframe_poses=keyframe_poses,
            loops=loops,
            rejected_loops=[loop for loop in loops if loop.weight < 0.5],
            odometry_noise_scale=graph.odometry_scale,
            timings={**result.timings, "refine": seconds, "total": result.timings["total"] + seconds},
        )
        refined.poses = refined.frame_poses(keyframe_poses)
        return refined

    def _result(
        self, frontend: Frontend, keyframe_poses: dict[int, np.ndarray], skipped: list[int], timings: dict[str, float]
    ) -> SlamResult:
        odometry_poses = np.asarray(frontend.poses)
        keyframe_of_frame = np.asarray(frontend.keyframe_of_frame)
        result = SlamResult(
            timestamps=np.asarray(frontend.timestamps, dtype=np.float64),
            poses=np.empty((0, 4, 4)),
            odometry_poses=odometry_poses,
            keyframes=frontend.keyframes,
            keyframe_of_frame=keyframe_of_frame,
            T_keyframe_frame=_relative_to_keyframes(frontend.keyframes, keyframe_of_frame, odometry_poses),
            graph=self.module.graph,
            values=self.module.values,
            keyframe_poses=keyframe_poses,
            loops=list(self.module.loops),
            rejected_loops=self.module.rejected_loops(),
            skipped_frames=skipped,
            odometry_noise_scale=self.module.pose_graph.odometry_scale,
            config=self.module.config,
            timings=timings,
        )
        result.poses = result.frame_poses(keyframe_poses)
        return result


def _with_progress(frames: Iterable, progress: bool, desc: str = "sandro-slam") -> Iterable:
    if not progress:
        return frames
    from tqdm import tqdm

    return tqdm(frames, unit="frame", desc=desc)


def _relative_to_keyframes(keyframes: list[Keyframe], keyframe_of_frame: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(F, 4, 4) each frame's pose relative to its keyframe's."""
    T_keyframe_world = {keyframe.key: np.linalg.inv(keyframe.T_world_keyframe) for keyframe in keyframes}
    return np.stack([T_keyframe_world[int(key)] for key in keyframe_of_frame]) @ poses


def _needs_head(config: SlamConfig, odometry: GivenPoses | None) -> bool:
    """Whether `run` reads the first scans ahead for the sweep period of their azimuth times (the scale aside)."""
    return odometry is None and _sweep_rotation(config) is not None


def _told_sweep_times(
    config: SlamConfig, head: list[tuple[int, Scan]], scans: Iterator[tuple[int, Scan]]
) -> tuple[list[tuple[int, Scan]], float | None]:
    """`sweep_times: auto` made "none" or a turning direction: `detected_rotation` on up to TEST_SCANS scans with
    points, read on from `head`, where its first scan with points has no per-point times. The head as read, and the
    seconds the test took (None where it did not run)."""
    head = head or _first_scans(scans, 1)
    first = next((scan for _, scan in head if len(scan.points)), None)
    if first is None or len(first.times):
        config.sweep_times = "none"
        return head, None
    head = head + _first_scans(scans, TEST_SCANS - sum(len(scan.points) > 0 for _, scan in head))
    clouds = [scan.points for _, scan in head if len(scan.points)][:TEST_SCANS]
    start = time.perf_counter()
    rotation = detected_rotation(clouds, config.odometry, _head_period(head))
    config.sweep_times = rotation or "none"
    return head, time.perf_counter() - start


def _head_period(head: list[tuple[int, Scan]]) -> float:
    """The sweep period [s] of the scans read ahead: from the stamps of the first SCANS with points."""
    return sweep_period([scan.timestamp for _, scan in head if len(scan.points)][:SCANS])


def _sweep_rotation(config: SlamConfig) -> Rotation | None:
    """The turning direction whose azimuth times scans without per-point times get (None: none)."""
    return config.sweep_times if config.sweep_times in ("clockwise", "counterclockwise") else None


def _first_scans(scans: Iterator[tuple[int, Scan]], count: int = SCANS) -> list[tuple[int, Scan]]:
    """Items of `scans` up to the `count`-th that has points (all of them if fewer)."""
    head, with_points = [], 0
    for item in scans:
        head.append(item)
        with_points += len(item[1].points) > 0
        if with_points >= count:
            break
    return head


def _same_sweep(scan: Scan, previous: Scan | None) -> bool:
    """Whether `scan` repeats `previous`: the same stamp and the same points."""
    return (
        previous is not None
        and scan.timestamp == previous.timestamp
        and scan.points.shape == previous.points.shape
        and np.array_equal(scan.points, previous.points)
    )


def _finite(scan: Scan) -> Scan:
    """The scan without its non-finite points (perhaps none left)."""
    if np.isfinite(scan.points.sum()):  # one reduction for clean scans
        return scan
    finite = np.all(np.isfinite(scan.points), axis=1)
    times = scan.times[finite] if len(scan.times) else scan.times
    return Scan(scan.timestamp, scan.points[finite], times)
