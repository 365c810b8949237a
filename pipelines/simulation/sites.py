"""Seeded worlds of the evaluation suite, each with the ways through it that the simulated LiDAR follows.

A `Site` is a `World` and named paths: (K, 2) waypoints in world x, y [m] (z up, ground or floor at
z = 0), followed in order along straight segments whose corners the caller rounds with arcs (radius up
to 6 m driving, 1.5 m walking). A path whose last waypoint equals its first is a closed loop, driven
for several laps. An "out_and_back" path is open and shaped like a lollipop: out along a way, once
around a small loop at the far end, back along the same way in the opposite direction (a little past
the start), so that it revisits places facing the other way without any U-turn.

Every segment keeps its margin from every surface that is not horizontal (`World.clearance`): 3 m
(`CLEARANCE`), 4 m along the campus roads (`ROAD_CLEARANCE`) and 0.8 m indoors (`INDOOR_CLEARANCE`).
No turn is sharper than 95 degrees, every segment is long enough for the arcs of its corners at the
largest radius, and the arcs keep the margin too. The paths are fixed by the layout or follow its
seeded rooms; the clutter placed at random is kept clear of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipelines.simulation.world import (
    CityLayout,
    Mesh,
    World,
    build_city,
    cylinder,
    ellipsoid,
    merge_meshes,
    oriented_box,
)

CLEARANCE = 3.0  # [m] from a path to the nearest obstacle
ROAD_CLEARANCE = 4.0  # [m] along the campus roads
INDOOR_CLEARANCE = 0.8  # [m] in the office

_SLACK = 0.3  # [m] added to every margin when placing clutter: paths are checked at samples 0.5 m apart


@dataclass(frozen=True, eq=False)
class Site:
    """A world and its named paths, (K, 2) world x, y waypoints [m] each; closed when last == first."""

    world: World
    paths: dict[str, np.ndarray]


def _samples(path: np.ndarray, step: float = 0.5) -> np.ndarray:
    """Points (M, 2) [m] along the straight segments of `path` (K, 2), at most `step` [m] apart."""
    pieces = [path[-1:]]
    for a, b in zip(path[:-1], path[1:]):
        count = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        pieces.append(a + np.linspace(0.0, 1.0, count, endpoint=False)[:, None] * (b - a))
    return np.concatenate(pieces)


def _rectangle_gaps(points: np.ndarray, centres: np.ndarray, halves: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Distances (M, R) [m] from points (M, 2) to R oriented rectangles (0 inside): centres (R, 2) [m],
    half sizes (R, 2) [m] along their own axes, yaws (R,) [rad] counter-clockwise from world x."""
    d = points[:, None, :] - centres[None]
    c, s = np.cos(yaws), np.sin(yaws)
    local = np.stack([c * d[..., 0] + s * d[..., 1], c * d[..., 1] - s * d[..., 0]], axis=-1)
    return np.linalg.norm(np.maximum(np.abs(local) - halves, 0.0), axis=-1)


class _FreeSpace:
    """The ground left for clutter: footprints (oriented rectangles in x, y [m]) must keep each path's
    margin and stay apart from the footprints claimed before them."""

    def __init__(self, keep_clear: Sequence[tuple[np.ndarray, float]]) -> None:
        """keep_clear: (waypoints (K, 2) [m], margin [m]) pairs; a single waypoint keeps a disc clear."""
        samples = [_samples(path) for path, _ in keep_clear]
        self._points = np.concatenate(samples)
        self._margins = np.concatenate(
            [np.full(len(s), margin + _SLACK) for s, (_, margin) in zip(samples, keep_clear)]
        )
        self._outlines = np.zeros((0, 2))  # points every metre around the claimed footprints
        self._claimed = np.zeros((0, 5))  # rows centre x, y, half x, y, yaw

    def fits(
        self, centre: np.ndarray, half: np.ndarray, yaw: float = 0.0, apart: float = 0.0, setback: float = 0.0
    ) -> bool:
        """Whether a footprint keeps every path margin plus `setback` [m], keeps `apart` [m] from every
        claimed footprint and has its centre outside them."""
        rectangle = (np.atleast_2d(centre), np.atleast_2d(half), np.atleast_1d(yaw))
        if np.any(_rectangle_gaps(self._points, *rectangle)[:, 0] < self._margins + setback):
            return False
        if np.any(_rectangle_gaps(self._outlines, *rectangle) < apart):
            return False
        inside = _rectangle_gaps(
            np.atleast_2d(centre), self._claimed[:, :2], self._claimed[:, 2:4], self._claimed[:, 4]
        )
        return not np.any(inside == 0.0)

    def claim(self, centre: np.ndarray, half: np.ndarray, yaw: float = 0.0) -> None:
        """Marks a footprint as taken."""
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * half
        c, s = np.cos(yaw), np.sin(yaw)
        outline = _samples(corners, step=1.0) @ np.array([[c, s], [-s, c]]) + centre
        self._outlines = np.concatenate([self._outlines, outline])
        self._claimed = np.vstack([self._claimed, [*centre, *half, yaw]])

    def take(
        self, centre: np.ndarray, half: np.ndarray, yaw: float = 0.0, apart: float = 0.0, setback: float = 0.0
    ) -> bool:
        """Claims the footprint if it fits; whether it did."""
        if not self.fits(centre, half, yaw, apart, setback):
            return False
        self.claim(centre, half, yaw)
        return True


def _alongside(
    rng: np.random.Generator, path: np.ndarray, offset: float, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points beside every segment of `path` (K, 2): `offset` [m] to its left (negative: right), about
    `spacing` [m] apart along it (jittered by up to a quarter spacing); and the segments' headings [rad]."""
    points, headings = [], []
    for a, b in zip(path[:-1], path[1:]):
        length = np.linalg.norm(b - a)
        along = np.arange(rng.uniform(0.0, spacing), length, spacing)
        along = along + rng.uniform(-0.25, 0.25, size=len(along)) * spacing
        u = (b - a) / length
        points.append(a + along[:, None] * u + offset * np.array([-u[1], u[0]]))
        headings.append(np.full(len(along), np.arctan2(u[1], u[0])))
    return np.concatenate(points), np.concatenate(headings)


def _shell(size_x: float, size_y: float, height: float, thickness: float) -> list[list[float]]:
    """Boxes [xmin, ymin, zmin, xmax, ymax, zmax] [m] enclosing the floor [0, size_x] x [0, size_y]: four
    outer walls `thickness` [m] thick outside it and a ceiling slab from z = height up."""
    t = thickness
    return [
        [-t, -t, 0.0, size_x + t, 0.0, height],
        [-t, size_y, 0.0, size_x + t, size_y + t, height],
        [-t, 0.0, 0.0, 0.0, size_y, height],
        [size_x, 0.0, 0.0, size_x + t, size_y, height],
        [-t, -t, height, size_x + t, size_y + t, height + t],
    ]


def build_city_site(seed: int, layout: CityLayout = CityLayout()) -> Site:
    """The seeded box city (`build_city`) and paths along its street centrelines (p = layout.pitch):
    "loop", the rectangle `layout.loop` around the two central blocks (6 p a lap); "big_loop", around
    the four blocks of x, y in [0, 2 p] (8 p); "out_and_back", east along y = 0 from x = -p / 2 to
    x = 3 p, around the block north-west of there and back west to x = -0.8 p. Needs at least 4 x 3
    blocks."""
    if layout.blocks_x < 4 or layout.blocks_y < 3:
        raise ValueError(f"the city site needs at least 4 x 3 blocks, got {layout.blocks_x} x {layout.blocks_y}")
    p = layout.pitch
    x0, y0, x1, y1 = layout.loop
    paths = {
        "loop": np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]),
        "big_loop": np.array([[0.0, 0.0], [2 * p, 0.0], [2 * p, 2 * p], [0.0, 2 * p], [0.0, 0.0]]),
        "out_and_back": np.array([[-0.5, 0.0], [3.0, 0.0], [3.0, 1.0], [2.0, 1.0], [2.0, 0.0], [-0.8, 0.0]]) * p,
    }
    return Site(build_city(seed, layout), paths)


_GARAGE_SIZE = (100.0, 50.0)  # x, y extent of the floor [m]
_GARAGE_HEIGHT = 3.0  # underside of the ceiling slab [m]
_PILLAR_X = 10.0 + 8.0 * np.arange(11)  # pillar columns [m]; the 10 spacings between them hold 3 bays each
_PILLAR_Y = np.array([7.0, 19.0, 31.0, 43.0])  # pillar rows [m]
_BAY_ROWS = np.array([4.6, 21.4, 28.6, 45.4])  # y of a parked car's centre: south wall, middle strip, north wall


def _garage_features(rng: np.random.Generator) -> tuple[list[list[float]], set[tuple[int, int]]]:
    """The irregular structure, boxes [m], and the (bay row, pillar spacing) pairs it takes from the
    parking: a walled ramp over two spacings of the middle strip, a stair core in a wall row and a wall
    segment along the middle of the strip. The strip's 9th spacing (x 74-82) stays free: a cross lane."""
    h = _GARAGE_HEIGHT
    ramp = int(rng.integers(0, 7))
    x = _PILLAR_X[ramp] + 0.6, _PILLAR_X[ramp + 2] - 0.6
    boxes = [[x[0], 19.6, 0.0, x[1], 30.4, h]]
    taken = {(row, spacing) for row in (1, 2) for spacing in (ramp, ramp + 1, 8)}
    row, spacing = int(rng.choice([0, 3])), int(rng.integers(0, 10))
    y = (0.0, 5.5) if row == 0 else (44.5, 50.0)
    boxes.append([_PILLAR_X[spacing] + 1.5, y[0], 0.0, _PILLAR_X[spacing] + 6.5, y[1], h])
    taken.add((row, spacing))
    run = np.arange(0, ramp) if ramp >= 3 else np.arange(ramp + 2, 8)  # 3 or more spacings beside the ramp
    first = int(rng.integers(0, len(run) - 1))
    last = min(len(run) - 1, first + int(rng.integers(1, 4)))  # 2-4 spacings
    x = _PILLAR_X[run[first]] + 0.5, _PILLAR_X[run[last] + 1] - 0.5
    boxes.append([x[0], 24.85, 0.0, x[1], 25.15, float(rng.choice([1.2, h]))])
    return boxes, taken


def _parked_cars(rng: np.random.Generator, taken: set[tuple[int, int]]) -> list[Mesh]:
    """Cars in about half the free bays, parked across the rows (long axis along y) a little off the bay
    centre and askew; one in six a taller, longer van."""
    cars = []
    for row, y in enumerate(_BAY_ROWS):
        for spacing, x in enumerate(_PILLAR_X[:-1]):
            for bay in (-1, 0, 1):
                if (row, spacing) in taken or rng.random() < 0.5:
                    continue
                van = rng.random() < 1 / 6
                length = rng.uniform(4.9, 5.3) if van else rng.uniform(4.3, 4.8)
                height = rng.uniform(1.9, 2.1) if van else rng.uniform(1.4, 1.65)
                centre = [x + 4.0 + 2.6 * bay + rng.uniform(-0.08, 0.08), y + rng.uniform(-0.2, 0.2), 0.5 * height]
                half = [0.5 * length, 0.5 * rng.uniform(1.75, 1.95), 0.5 * height]
                cars.append(oriented_box(centre, half, 0.5 * np.pi + np.deg2rad(rng.uniform(-1.5, 1.5))))
    return cars


def build_garage(seed: int) -> Site:
    """One level of an underground car park: floor x in [0, 100], y in [0, 50] m at z = 0, 0.3 m walls
    round it and a ceiling slab from z = 3 m. Square 0.6 m pillars stand on a grid 8 m apart along x
    (x = 10 .. 90) and 12 m along y (y = 7, 19, 31, 43): the repeated structure that lets registration
    slip by one spacing. Two 12 m wide lanes run along x between pillar rows (centrelines y = 13 and
    37), joined by pillar-free cross lanes at both ends (x = 5, 95) and one across the middle strip
    (x = 78). Bays, three per pillar spacing, face the lanes from both walls and from both sides of the
    middle strip; about half hold a car (4.3-4.8 x 1.75-1.95 x 1.4-1.65 m) or van, slightly off-centre
    and askew. A walled ramp and a wall segment in the middle strip and a stair core in a wall row,
    placed at random, keep registration well-posed.

    Paths (3 m clear): "loop", 228 m round the lanes; "out_and_back", east along the y = 13 lane, round
    the east end of the middle strip (back south through the x = 78 cross lane) and back west.
    """
    rng = np.random.default_rng(seed)
    size_x, size_y = _GARAGE_SIZE
    h = _GARAGE_HEIGHT
    boxes = _shell(size_x, size_y, h, thickness=0.3)
    boxes += [[x - 0.3, y - 0.3, 0.0, x + 0.3, y + 0.3, h] for x in _PILLAR_X for y in _PILLAR_Y]
    features, taken = _garage_features(rng)
    world = World(
        np.array(boxes + features), (-0.3, -0.3, size_x + 0.3, size_y + 0.3), *merge_meshes(_parked_cars(rng, taken))
    )
    paths = {
        "loop": np.array([[5.0, 13.0], [95.0, 13.0], [95.0, 37.0], [5.0, 37.0], [5.0, 13.0]]),
        "out_and_back": np.array([[14.0, 13.0], [95.0, 13.0], [95.0, 37.0], [78.0, 37.0], [78.0, 13.0], [8.0, 13.0]]),
    }
    return Site(world, paths)


_CAMPUS_SIZE = (300.0, 250.0)  # x, y extent in which things are placed [m]
_CAMPUS_ROADS = {
    "loop": np.array([[50, 40], [200, 30], [250, 90], [230, 160], [110, 170], [45, 120], [50, 40]], dtype=float),
    "out_and_back": np.array([[20, 205], [280, 205], [280, 240], [240, 240], [240, 205], [10, 205]], dtype=float),
}
_CAMPUS_WALK = np.array([[100, 75], [170, 70], [195, 110], [150, 135], [95, 120], [100, 75]], dtype=float)
_CAMPUS_LAWNS = ((np.array([[142.0, 100.0]]), 20.0), (np.array([[150.0, 230.0]]), 16.0))  # open discs [m]


def _building(rng: np.random.Generator, space: _FreeSpace) -> list[Mesh]:
    """One building at a random place and yaw, about 10 m back from the ways and 6 m from other buildings: a box
    15-45 x 10-20 m, 5-25 m high, and in four of ten cases a lower wing at one end making an L. Nothing
    if it does not fit."""
    centre, yaw = rng.uniform((0.0, 0.0), _CAMPUS_SIZE), rng.uniform(0.0, np.pi)
    half = rng.uniform((7.5, 5.0), (22.5, 10.0))
    height = rng.uniform(5.0, 25.0)
    footprints = [(centre, half, height)]
    if rng.random() < 0.4:
        wing = rng.uniform((4.0, 5.0), (7.0, 12.5))  # half width along the main axis, half length across it
        side = rng.choice([-1.0, 1.0], size=2)
        local = side * [half[0] - wing[0], half[1] + wing[1] - 0.5]  # flush with an end, 0.5 m into the box
        c, s = np.cos(yaw), np.sin(yaw)
        footprints.append(
            (centre + [c * local[0] - s * local[1], s * local[0] + c * local[1]], wing, height * rng.uniform(0.4, 1.0))
        )
    if not all(space.fits(c, w, yaw, apart=6.0, setback=6.0) for c, w, _ in footprints):
        return []
    for c, w, _ in footprints:
        space.claim(c, w, yaw)
    return [oriented_box([*c, 0.5 * z], [*w, 0.5 * z], yaw) for c, w, z in footprints]


def _tree(rng: np.random.Generator, space: _FreeSpace, at: np.ndarray, crown: tuple[float, float]) -> list[Mesh]:
    """A tree at `at` (x, y) [m] if its crown fits: trunk 0.25-0.35 m in radius up to the middle of an
    ellipsoid crown of horizontal radius in `crown` [m], bottom 2.5-4 m up."""
    radius, bottom = rng.uniform(*crown), rng.uniform(2.5, 4.0)
    depth = radius * rng.uniform(0.7, 1.1)
    if not space.take(at, np.array([radius, radius]), apart=0.5):
        return []
    trunk = cylinder(at, rng.uniform(0.25, 0.35), 0.0, bottom + depth, sides=10)
    return [trunk, ellipsoid([*at, bottom + depth], [radius, radius, depth])]


def _lamp(space: _FreeSpace, at: np.ndarray, height: float) -> list[Mesh]:
    """A lamp post at `at` (x, y) [m], `height` [m] tall with a small head, if it fits."""
    if not space.take(at, np.array([0.3, 0.3]), apart=0.5):
        return []
    return [cylinder(at, 0.08, 0.0, height, sides=8), oriented_box([*at, height], [0.3, 0.15, 0.1])]


def _campus_clutter(rng: np.random.Generator, space: _FreeSpace) -> list[Mesh]:
    """Lamp posts along the roads (5 m off) and the walk (3.8 m off), benches beside the walk, trees in
    rows along the roads (8 m off) and the walk (6 m off), in random clusters and alone, low walls at
    random."""
    parts = []
    for road in _CAMPUS_ROADS.values():
        for at in _alongside(rng, road, 5.0, spacing=35.0)[0]:
            parts += _lamp(space, at, rng.uniform(6.0, 8.0))
    for at in _alongside(rng, _CAMPUS_WALK, -3.8, spacing=25.0)[0]:
        parts += _lamp(space, at, rng.uniform(3.5, 4.5))
    for at, heading in zip(*_alongside(rng, _CAMPUS_WALK, 4.0, spacing=30.0)):
        if space.take(at, np.array([0.9, 0.3]), heading, apart=0.5):
            parts.append(oriented_box([*at, 0.225], [0.9, 0.3, 0.225], heading))
    rows = [(road, 8.0, (2.0, 3.0)) for road in _CAMPUS_ROADS.values()] + [(_CAMPUS_WALK, 6.0, (2.0, 2.5))]
    for path, offset, crown in rows:  # offset [m] to both sides, crown radii [m]
        for side in (-1.0, 1.0):
            for at in _alongside(rng, path, side * offset, spacing=12.0)[0]:
                parts += _tree(rng, space, at, crown)
    for _ in range(int(rng.integers(12, 19))):
        middle, spread = rng.uniform((0.0, 0.0), _CAMPUS_SIZE), rng.uniform(5.0, 10.0)
        for at in middle + spread * rng.standard_normal((int(rng.integers(6, 21)), 2)):
            parts += _tree(rng, space, at, (2.0, 5.0))
    for at in rng.uniform((0.0, 0.0), _CAMPUS_SIZE, size=(80, 2)):
        parts += _tree(rng, space, at, (2.0, 5.0))
    for _ in range(20):
        at, yaw = rng.uniform((0.0, 0.0), _CAMPUS_SIZE), rng.uniform(0.0, np.pi)
        half, height = np.array([rng.uniform(2.5, 10.0), 0.15]), rng.uniform(0.5, 1.2)
        if space.take(at, half, yaw, apart=1.0):
            parts.append(oriented_box([*at, 0.5 * height], [*half, 0.5 * height], yaw))
    return parts


def build_campus(seed: int) -> Site:
    """A campus or park on flat ground, things placed in x in [0, 300], y in [0, 250] m: about 20 buildings
    at random yaw (boxes and L-shapes, 5-25 m high), trees (trunks 0.25-0.35 m in radius, crowns 2-5 m
    in radius from 2.5-4 m up) in rows along the ways and in clusters, lamp posts, benches and low walls,
    with open lawns between.

    Paths: "loop", a 584 m hexagonal ring road for a car (4 m clear); "walk", a 270 m loop through the
    park inside it for a walker (3 m clear); "out_and_back", 370 m out along a road north of the ring and
    around a block at its east end, then back (4 m clear).
    """
    rng = np.random.default_rng(seed)
    keep_clear = [(road, ROAD_CLEARANCE) for road in _CAMPUS_ROADS.values()] + [(_CAMPUS_WALK, CLEARANCE)]
    space = _FreeSpace(keep_clear + list(_CAMPUS_LAWNS))
    parts = [part for _ in range(300) for part in _building(rng, space)]
    parts += _campus_clutter(rng, space)
    size_x, size_y = _CAMPUS_SIZE
    world = World(np.zeros((0, 6)), (-60.0, -60.0, size_x + 60.0, size_y + 60.0), *merge_meshes(parts))
    return Site(world, {**_CAMPUS_ROADS, "walk": _CAMPUS_WALK})


_OFFICE_SIZE = (50.0, 30.0)  # x, y extent of the floor [m]
_OFFICE_HEIGHT = 3.0  # underside of the ceiling slab [m]
_RING = (6.5, 6.5, 43.5, 23.5)  # corridor ring centreline xmin, ymin, xmax, ymax [m]
_CORRIDOR_WALL = 1.2  # centreline to the middle of a corridor wall [m]: 2.2 m clear with 0.2 m walls
_LANE = 1.8  # from a room's corridor wall to the way through a room with two doors [m]


def _partition(rng: np.random.Generator, start: float, end: float) -> np.ndarray:
    """Edges (n + 1,) [m] splitting [start, end] into n rooms of random widths near 4-8 m."""
    length = end - start
    count = int(np.clip(round(length / 6.0), np.ceil(length / 8.0), max(1.0, length // 4.0)))
    widths = 4.0 + (length - 4.0 * count) * rng.dirichlet(np.full(count, 3.0))
    return start + np.concatenate([[0.0], np.cumsum(widths)])


def _wall(
    axis: int, at: float, span: tuple[float, float], thickness: float, openings: Sequence[tuple[float, float]] = ()
) -> list[list[float]]:
    """Boxes [m] of a straight wall along world x (axis 0) or y (axis 1), centred on `at` across it, from
    span[0] to span[1] along it, floor to ceiling, broken by `openings` ((centre, width) [m] along it)."""
    edges = [span[0]] + [e for centre, width in sorted(openings) for e in (centre - 0.5 * width, centre + 0.5 * width)]
    edges.append(span[1])
    across = (at - 0.5 * thickness, at + 0.5 * thickness)
    boxes = []
    for lo, hi in zip(edges[::2], edges[1::2]):
        if hi > lo:
            (x0, x1), (y0, y1) = ((lo, hi), across) if axis == 0 else (across, (lo, hi))
            boxes.append([x0, y0, 0.0, x1, y1, _OFFICE_HEIGHT])
    return boxes


@dataclass(frozen=True)
class _Room:
    """A room's inside (x0, y0, x1, y1) [m] and the points just inside its doors (P, 2) [m]."""

    inside: tuple[float, float, float, float]
    doorsteps: np.ndarray


def _row_of_rooms(
    rng: np.random.Generator, axis: int, edges: np.ndarray, across: tuple[float, float], door_side: int, wide: int = -1
) -> tuple[list[list[float]], list[tuple[float, float]], list[_Room]]:
    """Rooms side by side along world x (axis 0) or y (axis 1) between `edges` [m], spanning `across`
    (wall centres, [m]) the other way, with their doors in the wall at across[door_side].

    Returns the partition walls (0.15 m), the door openings (centre, width) of the door wall, and the
    rooms. Each room has a 1 m door at random; room `wide` has two 2 m doors 1.5 m in from its ends.
    """
    walls, doors, rooms = [], [], []
    inward = 1.0 if door_side == 0 else -1.0
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        walls += _wall(1 - axis, lo, across, 0.15) if k else []
        centres = [lo + 1.5, hi - 1.5] if k == wide else [rng.uniform(lo + 0.8, hi - 0.8)]
        doors += [(c, 2.0 if k == wide else 1.0) for c in centres]
        steps = np.array([[c, across[door_side] + inward] for c in centres])
        a0, a1 = lo + 0.075, hi - 0.075
        b0, b1 = across[0] + 0.1, across[1] - 0.1
        rooms.append(_Room((a0, b0, a1, b1) if axis == 0 else (b0, a0, b1, a1), steps if axis == 0 else steps[:, ::-1]))
    return walls, doors, rooms


def _furnish(rng: np.random.Generator, space: _FreeSpace, room: _Room) -> list[list[float]]:
    """1-5 desks (1.6 x 0.8 x 0.75 m) and 0-2 cabinets (0.9 x 0.45 x 1.9 m) against the walls of `room`,
    where they fit: 0.8 m apart and clear of the paths and doorways."""
    x0, y0, x1, y1 = room.inside
    boxes = []
    for size in [(1.6, 0.8, 0.75)] * int(rng.integers(1, 6)) + [(0.9, 0.45, 1.9)] * int(rng.integers(0, 3)):
        side = int(rng.integers(0, 4))  # against the wall at y0, y1, x0, x1
        along_x = side < 2
        length, depth, height = size
        half = np.array([length, depth] if along_x else [depth, length]) / 2
        lo, hi = np.array([x0, y0]) + half + 0.05, np.array([x1, y1]) - half - 0.05
        centre = rng.uniform(lo, hi)
        centre[int(along_x)] = (lo if side % 2 == 0 else hi)[int(along_x)]  # back against that wall
        if space.take(centre, half, apart=0.8):
            boxes.append([*(centre - half), 0.0, *(centre + half), height])
    return boxes


def _open_plan(
    rng: np.random.Generator, space: _FreeSpace, x: tuple[float, float]
) -> tuple[list[list[float]], list[Mesh]]:
    """Furniture boxes and round pillars (0.25 m radius, meshes) of the open-plan area between x[0] and
    x[1] [m] across the inner block: four pillars, then blocks of two desks facing each other (1.6 x 1.6 x
    0.75 m) with a 1.2 m high screen between them, where they fit 1 m apart and clear of the paths."""
    third = (x[1] - x[0]) / 3.0
    spine = 0.5 * (_RING[1] + _RING[3])
    pillars = [np.array([x[0] + k * third, spine + side * 3.5]) for k in (1, 2) for side in (-1, 1)]
    for at in pillars:
        space.claim(at, np.array([0.25, 0.25]))
    boxes = []
    for _ in range(30):
        along_x = rng.random() < 0.5
        half = np.array([0.8, 0.8]) * ([2.0, 1.0] if along_x else [1.0, 2.0])
        centre = rng.uniform(np.array([x[0] + 0.1, _RING[1]]) + half, np.array([x[1] - 0.1, _RING[3]]) - half)
        if space.take(centre, half, apart=1.0):
            screen = np.array([half[0], 0.025] if along_x else [0.025, half[1]])
            boxes += [
                [*(centre - half), 0.0, *(centre + half), 0.75],
                [*(centre - screen), 0.0, *(centre + screen), 1.2],
            ]
    return boxes, [cylinder(at, 0.25, 0.0, _OFFICE_HEIGHT, sides=12) for at in pillars]


def _office_layout(
    rng: np.random.Generator,
) -> tuple[list[list[float]], list[_Room], list[tuple[float, float]], tuple[float, float]]:
    """The office's walls (boxes [m]), its rooms, the x extents [m] of the south and north rooms with two
    doors, and the x extent [m] of the open-plan area."""
    size_x, size_y = _OFFICE_SIZE
    rx0, ry0, rx1, ry1 = _RING
    w = _CORRIDOR_WALL
    spine = 0.5 * (ry0 + ry1)
    west = rng.uniform(17.0, 21.0)
    plan = (west, west + rng.uniform(10.0, 13.0))
    inner_x, inner_y = (rx0 + w - 0.1, rx1 - w + 0.1), (ry0 + w - 0.1, ry1 - w + 0.1)
    opening = (0.5 * (plan[0] + plan[1]), plan[1] - plan[0])
    walls = {  # the corridor's walls (axis, centre across, span along) [m] and their openings
        (0, ry0 - w, (0.0, size_x)): [],
        (0, ry1 + w, (0.0, size_x)): [],
        (1, rx0 - w, (0.0, size_y)): [],
        (1, rx1 + w, (0.0, size_y)): [],
        (0, ry0 + w, inner_x): [opening],
        (0, ry1 - w, inner_x): [opening],
        (1, rx0 + w, inner_y): [],
        (1, rx1 - w, inner_y): [],
    }
    south, north, west, east, inner_south, inner_north = list(walls)[:6]
    rows, visits = [], []  # rows: (door wall, partition edges, across, door side, room with two doors)
    for wall, across, door_side in ((south, (0.0, ry0 - w), 1), (north, (ry1 + w, size_y), 0)):
        start = rng.uniform(12.0, 24.0)
        visits.append((start, start + rng.uniform(7.0, 8.0)))
        left, right = _partition(rng, rx0 - w, visits[-1][0]), _partition(rng, visits[-1][1], rx1 + w)
        rows.append((wall, np.concatenate([left, right]), across, door_side, len(left) - 1))
    for wall, across, door_side in ((west, (0.0, rx0 - w), 1), (east, (rx1 + w, size_x), 0)):
        rows.append((wall, _partition(rng, ry0 - w, ry1 + w), across, door_side, -1))
    for wall, across, door_side in ((inner_south, (ry0 + w, spine), 0), (inner_north, (spine, ry1 - w), 1)):
        for x in ((rx0 + w, plan[0]), (plan[1], rx1 - w)):
            rows.append((wall, _partition(rng, *x), across, door_side, -1))
    boxes, rooms = _shell(size_x, size_y, _OFFICE_HEIGHT, thickness=0.3), []
    for wall, edges, across, door_side, wide in rows:
        partitions, openings, row = _row_of_rooms(rng, wall[0], edges, across, door_side, wide)
        boxes += partitions
        walls[wall] += openings
        rooms += row
    boxes += [box for (axis, at, span), openings in walls.items() for box in _wall(axis, at, span, 0.2, openings)]
    for x in ((rx0 + w, plan[0]), (plan[1], rx1 - w)):
        boxes += _wall(0, spine, x, 0.15)
    for x in plan:
        boxes += _wall(1, x, (ry0 + w, ry1 - w), 0.15)
    return boxes, rooms, visits, plan


def build_office(seed: int) -> Site:
    """One office floor: x in [0, 50], y in [0, 30] m at z = 0, 0.3 m outer walls and a ceiling slab from
    z = 3 m. A 2.2 m corridor runs round a ring (centreline x in [6.5, 43.5], y in [6.5, 23.5]) between
    0.2 m walls; rooms of random widths near 4-8 m line both sides, split by 0.15 m partitions: a band
    about 5 m deep between the ring and the outer walls (its corner squares closed cores), and two rows
    7 m deep back to back inside the ring. Each room has a 1 m door onto the corridor at random, one room
    on the south and one on the north band has two 2 m doors instead (the "rooms" path walks through
    them). An open-plan area 10-13 m wide, open to the corridor on both sides, crosses the inner block at
    random, with four round pillars and desk blocks; the rooms hold desks and cabinets against their walls.

    Paths for a walker (0.8 m clear): "loop", 108 m round the corridor ring; "rooms", the ring entering
    and leaving the two rooms with two doors (120 m); "out_and_back", south along the west corridor, east,
    north, back west to the open-plan area, south across it and back west and north past the start.
    """
    rng = np.random.default_rng(seed)
    boxes, rooms, visits, plan = _office_layout(rng)
    paths = _office_paths(visits, 0.5 * (plan[0] + plan[1]))
    space = _FreeSpace([(path, INDOOR_CLEARANCE) for path in paths.values()] + [(r.doorsteps, 0.9) for r in rooms])
    furniture, pillars = _open_plan(rng, space, plan)
    boxes += furniture + [box for room in rooms for box in _furnish(rng, space, room)]
    size_x, size_y = _OFFICE_SIZE
    world = World(np.array(boxes), (-0.3, -0.3, size_x + 0.3, size_y + 0.3), *merge_meshes(pillars))
    return Site(world, paths)


def _office_paths(visits: list[tuple[float, float]], cross: float) -> dict[str, np.ndarray]:
    """The office's paths: `visits` holds the x extents [m] of the south and north rooms with two doors,
    `cross` the x [m] of the way across the open-plan area."""
    rx0, ry0, rx1, ry1 = _RING
    south = ry0 - _CORRIDOR_WALL - 0.1 - _LANE  # the ways through the two rooms
    north = ry1 + _CORRIDOR_WALL + 0.1 + _LANE
    (s0, s1), (n0, n1) = ((a + 1.5, b - 1.5) for a, b in visits)  # their doors
    ring = [[rx0, ry0], [rx1, ry0], [rx1, ry1], [rx0, ry1], [rx0, ry0]]
    rooms = [[rx0, ry0], [s0, ry0], [s0, south], [s1, south], [s1, ry0], [rx1, ry0], [rx1, ry1]]
    rooms += [[n1, ry1], [n1, north], [n0, north], [n0, ry1], [rx0, ry1], [rx0, ry0]]
    out = [[rx0, ry1 - 3.5], [rx0, ry0], [rx1, ry0], [rx1, ry1], [cross, ry1], [cross, ry0]]
    out += [[rx0, ry0], [rx0, ry1 - 1.5]]
    return {"loop": np.array(ring), "rooms": np.array(rooms), "out_and_back": np.array(out)}
