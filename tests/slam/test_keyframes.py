"""KeyframeBuilder: where keyframes start, what their submaps hold, a standstill folded; place recognition:
MapClosures' spacing and pickling, ring keys."""

import pickle
import tracemalloc

import gtsam
import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipelines.simulation import simulate_sequence
from sandro_core.geometry import transform_points
from sandro_slam.candidates import PlaceRecognition, RingKeyRecognition, radius_candidates, span_centres
from sandro_slam.config import KeyframeConfig, LoopDetectionConfig, SlamConfig
from sandro_slam.keyframes import ANCHOR_SCANS, FOLD_SCANS, KeyframeBuilder, keyframe_frames

REFERENCE = SlamConfig().resolved()  # every length at its reference value


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


def test_submaps_hold_each_voxel_once_in_the_keyframe_frame_within_the_radius():
    rng = np.random.default_rng(0)
    world = rng.uniform(-40.0, 40.0, size=(3000, 3))  # a static scene, seen from every pose
    config = KeyframeConfig(distance=10.0, angle_deg=30.0, submap_voxel=0.5, submap_radius=30.0)
    builder = KeyframeBuilder(config)
    poses = [_pose(x, yaw_deg=2.0 * x) for x in np.arange(0.0, 25.0, 2.5)]
    completed = []
    for index, T in enumerate(poses):
        keyframe = builder.add_scan(index, T, world @ T[:3, :3] - T[:3, 3] @ T[:3, :3])  # the scene in the scan frame
        if keyframe is not None:
            completed.append(keyframe)
    completed.append(builder.flush())

    # every 10 m of travel; the first keyframe's frame is the first scan with both changes of rotation known
    assert [k.anchor_frame for k in completed] == [2, 4, 8]
    assert [k.key for k in completed] == [0, 1, 2]
    for keyframe in completed:
        T = keyframe.T_world_keyframe
        expected = world @ T[:3, :3] - T[:3, 3] @ T[:3, :3]  # the scene in the keyframe frame
        voxels = np.floor(keyframe.points / config.submap_voxel).astype(int)
        assert len(np.unique(voxels, axis=0)) == len(keyframe.points)  # one point per voxel
        assert np.all(np.linalg.norm(keyframe.points, axis=1) <= config.submap_radius)
        inside = expected[np.linalg.norm(expected, axis=1) <= config.submap_radius]
        assert len(keyframe.points) == len(np.unique(np.floor(inside / config.submap_voxel).astype(int), axis=0))
        # every submap point is a scene point (each scan saw the same scene), moved into the keyframe frame
        distances, _ = cKDTree(expected).query(keyframe.points)
        assert distances.max() < 1e-9
    assert builder.flush() is None


def test_a_turn_starts_a_keyframe():
    builder = KeyframeBuilder(REFERENCE.keyframes.model_copy(update={"distance": 10.0, "angle_deg": 30.0}))
    points = np.ones((5, 3))
    assert builder.add_scan(0, _pose(0.0), points) is None  # the first keyframe starts
    assert builder.add_scan(1, _pose(1.0, 20.0), points) is None
    assert builder.add_scan(2, _pose(2.0, 35.0), points).key == 0  # 35 deg from the keyframe: the next one starts
    assert builder.current_key() == 1


def _keyframes(yaws: np.ndarray, distance: float = 10.0) -> tuple[list, list[int]]:
    """(the keyframes, the key each scan was given) of a drive 1 m a scan along x at the given yaws [deg]."""
    builder = KeyframeBuilder(REFERENCE.keyframes.model_copy(update={"distance": distance, "angle_deg": 360.0}))
    completed, keys = [], []
    for index, yaw in enumerate(yaws):
        completed.append(builder.add_scan(index, _pose(float(index), yaw), np.ones((5, 3))))
        keys.append(builder.current_key())
    return [k for k in completed if k is not None] + [builder.flush()], keys


def test_a_keyframe_is_anchored_on_a_scan_steady_on_both_sides():
    """Scan 10, where the keyframe is due, was registered 2.4 deg off (the scan of a sharp corner's start): the
    motions to it and from it, and from the scan after, show it; the keyframe's frame lies at scan 13's position,
    turned to the mean of its ten scans' rotations."""
    yaws = np.zeros(30)
    yaws[10] = 2.4
    keyframes, keys = _keyframes(yaws)
    assert keys[9:12] == [0, 1, 1]  # the scans belong to the keyframe from when it is due
    assert [k.anchor_frame for k in keyframes] == [2, 13, 20]  # the first: the first scan with both changes known
    np.testing.assert_allclose(keyframes[1].T_world_keyframe, _pose(13.0, yaw_deg=0.24), atol=1e-6)
    np.testing.assert_allclose(keyframes[2].T_world_keyframe, _pose(20.0), atol=1e-12)
    assert keyframes[1].travelled == pytest.approx(13.0)


def test_without_a_steady_scan_the_keyframe_is_anchored_on_the_steadiest():
    yaws = np.cumsum(0.1 * np.arange(30) ** 2)  # each scan's rotation rate changes more than any before it
    keyframes, _ = _keyframes(yaws)
    assert [k.anchor_frame for k in keyframes[1:]] == [10, 20]  # each keyframe's first scan: the smallest changes


def test_under_a_steady_sway_keyframes_are_anchored_near_their_start():
    """A walker's yaw sways on every scan: a change of rotation below most of the last scans' is steady."""
    keyframes, _ = _keyframes(3.0 * np.sin(np.arange(40) * 1.3))  # up to 6 deg from one scan to the next and back
    offsets = [k.anchor_frame - 10 * i for i, k in enumerate(keyframes)][1:]
    assert max(offsets) <= 2 < ANCHOR_SCANS - 1  # with the smallest recent change as the bar: 5, 0, 2


class _Recorder:
    """Stands in for MapClosures: records the keyframes it sees, finds nothing."""

    def __init__(self):
        self.seen = []

    def get_closures(self, key, points):
        self.seen.append(key)
        return []


def _standstill(builder: KeyframeBuilder, scans: int, seed: int = 0) -> list:
    """A sensor that moves 0.5 m, then stands still (its pose jittering by a few mm and mrad) for `scans` scans
    of one scene, each a new sample of 5000 of its points; returns the keyframes closed, the last flushed."""
    rng = np.random.default_rng(seed)
    scene = rng.uniform(-20.0, 20.0, size=(20000, 3))
    completed = []
    for index in range(scans):
        T = _pose(0.5 * min(index, 1) + rng.normal(0.0, 0.003), yaw_deg=rng.normal(0.0, 0.1))
        seen = scene[rng.choice(len(scene), 5000, replace=False)]
        completed.append(builder.add_scan(index, T, (seen - T[:3, 3]) @ T[:3, :3]))
    return [keyframe for keyframe in [*completed, builder.flush()] if keyframe is not None]


def test_a_standstill_folds_its_scans_into_the_same_submap(monkeypatch):
    config = KeyframeConfig(distance=10.0, angle_deg=30.0, submap_voxel=0.5, submap_radius=30.0)
    scans = int(3.5 * FOLD_SCANS)
    (folded,) = _standstill(KeyframeBuilder(config), scans)
    monkeypatch.setattr("sandro_slam.keyframes.FOLD_SCANS", 10**9)
    (whole,) = _standstill(KeyframeBuilder(config), scans)
    assert folded.anchor_frame == whole.anchor_frame
    np.testing.assert_array_equal(folded.T_world_keyframe, whole.T_world_keyframe)
    np.testing.assert_array_equal(np.unique(folded.points, axis=0), np.unique(whole.points, axis=0))


def test_a_standstill_holds_no_more_than_fold_scans_of_points():
    config = KeyframeConfig(distance=10.0, angle_deg=30.0, submap_voxel=0.5, submap_radius=30.0)
    scan_bytes = 5000 * 3 * 8
    tracemalloc.start()
    _standstill(KeyframeBuilder(config), 4 * FOLD_SCANS)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # the scans held, and their moved copies while they fold: about 3 x FOLD_SCANS scans (without folding, 12)
    assert peak < 4 * FOLD_SCANS * scan_bytes


def test_radius_candidates_are_the_keyframes_whose_submaps_cover_the_same_stretch():
    # Out along x with a keyframe every 10 m (each submap spans 10 m ahead of its anchor), back the other way.
    out = [0.0, 10.0, 20.0, 30.0, 40.0, 50.0]
    back = [44.0, 34.0, 24.0]
    anchors = {key: np.array([x, 0.0, 0.0]) for key, x in enumerate(out + back)}
    travelled = dict(zip(anchors, np.arange(len(anchors)) * 10.0))
    config = LoopDetectionConfig(radius=25.0, exclude_recent=30.0, max_candidates=1)
    centres = span_centres(anchors)
    assert centres[1][0] == 15.0 and centres[8][0] == 19.0  # the newest extrapolated: it covers 24 -> 14 m
    # The nearest anchor (20 m, its submap over 20-30 m) lies ahead of the way back; the submap over 10-20 m
    # covers what keyframe 8 has seen.
    assert radius_candidates(8, centres, travelled, config) == [1]
    # Driven again the same way, the submap over the same stretch starts at the nearest anchor.
    again = {**anchors, 9: np.array([12.0, 0.0, 0.0]), 10: np.array([22.0, 0.0, 0.0])}
    travelled_again = {**travelled, 9: 100.0, 10: 110.0}
    assert radius_candidates(10, span_centres(again), travelled_again, config) == [2]


def test_place_recognition_sees_keyframes_map_closures_spacing_apart():
    recognition = PlaceRecognition(REFERENCE.loops.model_copy(update={"map_closures_spacing": 15.0}))
    recognition._closures = _Recorder()
    travelled = {}
    for key in range(8):
        travelled[key] = 10.0 * key
        assert recognition.candidates(key, np.zeros((10, 3)), travelled) == []
    assert recognition._closures.seen == [0, 2, 4, 6]

    every = PlaceRecognition(REFERENCE.loops.model_copy(update={"map_closures_spacing": 0.0}))
    every._closures = _Recorder()
    for key in range(8):
        every.candidates(key, np.zeros((10, 3)), travelled)
    assert every._closures.seen == list(range(8))


def test_place_recognition_takes_any_64_bit_key():
    # gtsam symbols (x0, x1, ...) do not fit MapClosures' int ids: the ids are the keyframes' positions instead.
    recognition = PlaceRecognition(REFERENCE.loops.model_copy(update={"map_closures_spacing": 0.0}))
    recognition._closures = _Recorder()
    travelled = {}
    for index in range(3):
        key = gtsam.symbol("x", index)
        travelled[key] = 10.0 * index
        recognition.candidates(key, np.zeros((10, 3)), travelled)
    assert recognition._closures.seen == [0, 1, 2]


def _drive_submap() -> np.ndarray:
    """A simulated street seen over 10 frames, in the first frame's frame."""
    sequence = simulate_sequence(seed=1, frames=10)
    poses = sequence.poses_at(np.array([frame.timestamp for frame in sequence.frames()]))
    return np.concatenate(
        [
            transform_points(np.linalg.inv(poses[0]) @ pose, frame.points)
            for pose, frame in zip(poses, sequence.frames())
        ]
    )


def test_place_recognition_unpickled_finds_what_the_original_finds():
    # MapClosures does not pickle: the unpickled one rebuilds its database from the submaps it saw.
    submap = _drive_submap()
    other = np.random.default_rng(0).uniform([-30, -30, -2], [30, 30, 0], (20000, 3))  # another place: rough ground
    travelled = {key: 10.0 * key for key in range(41)}  # MapClosures matches only maps at least 4 keyframes apart
    original = PlaceRecognition(REFERENCE.loops.model_copy(update={"map_closures_spacing": 0.0}))
    original.candidates(0, submap, travelled)
    original.candidates(10, other, travelled)
    copy = pickle.loads(pickle.dumps(original))
    assert original.candidates(40, submap, travelled) == [0]
    assert copy.candidates(40, submap, travelled) == [0]


def test_ring_keys_find_a_place_seen_again_turned_and_skip_recent_keyframes():
    submap = _drive_submap()
    rng = np.random.default_rng(0)
    elsewhere = [rng.uniform([-30, -30, -2], [30, 30, 0], (20000, 3)), rng.uniform(-20, 20, (20000, 3))]
    turned = transform_points(np.linalg.inv(_pose(0.0, yaw_deg=100.0)), submap)  # the place seen heading elsewhere
    recognition = RingKeyRecognition(REFERENCE.loops)  # one candidate, at least 50 m of travel back
    travelled = {0: 0.0, 1: 20.0, 2: 40.0, 3: 70.0, 4: 100.0}
    assert recognition.candidates(0, submap, travelled) == []
    assert recognition.candidates(1, elsewhere[0], travelled) == []  # nothing 50 m back yet
    assert recognition.candidates(2, elsewhere[1], travelled) == []
    assert recognition.candidates(3, turned, travelled) == [0]
    assert recognition.candidates(4, turned, travelled) == [0]  # keyframe 3's ring key is the same, but 30 m back


def test_a_submap_does_not_change_when_the_caller_reuses_its_arrays():
    builder = KeyframeBuilder(REFERENCE.keyframes.model_copy(update={"distance": 10.0, "submap_voxel": 0.01}))
    pose, points = _pose(0.0), np.array([[1.0, 2.0, 0.0]])
    builder.add_scan(0, pose, points)
    pose[0, 3], points[:] = 5.0, 7.0  # a caller writing its next scan into the same buffers
    np.testing.assert_allclose(builder.flush().points, [[1.0, 2.0, 0.0]])


def test_under_sway_a_keyframe_frame_turns_as_its_scans_do_on_average():
    """Each scan's registered yaw jitters by 1 deg about the true heading 0: the frame's rotation, their mean, lies
    within half of that, where its anchor scan alone would hand its own jitter to every loop to it."""
    rng = np.random.default_rng(0)
    yaws = rng.normal(0.0, 1.0, 60)
    keyframes, keys = _keyframes(yaws, distance=20.0)
    frame_yaws = [np.degrees(np.arctan2(k.T_world_keyframe[1, 0], k.T_world_keyframe[0, 0])) for k in keyframes]
    assert np.max(np.abs(frame_yaws)) < 0.5
    assert np.max(np.abs(yaws[[k.anchor_frame for k in keyframes]])) > 0.5  # what the anchors alone would give
    # the benchmarks' truth of a keyframe frame, taken from the same poses, is the frame itself
    poses = np.array([_pose(float(i), yaw) for i, yaw in enumerate(yaws)])
    truths = keyframe_frames({k.key: k.anchor_frame for k in keyframes}, np.array(keys), poses)
    for keyframe in keyframes:
        np.testing.assert_allclose(truths[keyframe.key], keyframe.T_world_keyframe, atol=1e-12)
