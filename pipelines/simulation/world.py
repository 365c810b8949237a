"""A seeded box "city" on a ground plane: the geometry the simulated LiDAR sees.

Layout: a square grid of streets (centrelines every `pitch` metres in x and y); between them square
blocks whose edges sit `street_half_width` from the centrelines. Every block is the same template of
buildings, mirrored in x for odd block columns and in y for odd block rows, so blocks repeat every two
pitches along a street and face their mirror image across every street: the aliasing case for place
recognition and registration. Per-block changes (a courtyard tower, a lowered or raised building, a
vacant lot) and street furniture placed at random (poles, trees, parked cars, low walls) break the
symmetry enough for scan registration to be well-posed. All coordinates are world-frame metres, z up,
ground z = 0.

A `World` may also hold triangle meshes that are not axis-aligned boxes (the other sites in `sites`):
`oriented_box`, `cylinder` and `ellipsoid` make closed parts, `merge_meshes` joins them.

Flat facades parallel to the street leave pitch to the ground alone, and KISS-ICP then drifts in pitch
(its point-to-point matches on a plane follow the scan-line pattern, not the surface). Floor ledges and
tree crowns give horizontal edges, which hold that drift down (as 64 beams or narrower streets do too).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import ConvexHull

# Triangles of a box whose 8 corners are indexed by bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1),
# wound counter-clockwise seen from outside.
_BOX_TRIANGLES = np.array(
    [
        [0, 2, 1], [1, 2, 3],  # z min
        [4, 5, 6], [5, 7, 6],  # z max
        [0, 1, 4], [1, 5, 4],  # y min
        [2, 6, 3], [3, 6, 7],  # y max
        [0, 4, 2], [2, 4, 6],  # x min
        [1, 3, 5], [3, 7, 5],  # x max
    ],
    dtype=np.int64,
)  # fmt: skip


@dataclass(frozen=True)
class CityLayout:
    """Street grid: centrelines at x = pitch * (-1 .. blocks_x - 1), y = pitch * (-1 .. blocks_y - 1)."""

    pitch: float = 70.0  # distance between parallel street centrelines [m]
    street_half_width: float = 9.0  # centreline to building line [m]
    blocks_x: int = 4
    blocks_y: int = 3

    @property
    def block_size(self) -> float:
        """Edge of a (square) block [m]."""
        return self.pitch - 2.0 * self.street_half_width

    def block_origin(self, i: int, j: int) -> np.ndarray:
        """World (x, y) of the minimum corner of block column i, row j [m]."""
        return np.array([self.pitch * (i - 1), self.pitch * (j - 1)]) + self.street_half_width

    @property
    def loop(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the street centrelines around the two central blocks [m]."""
        return 0.0, 0.0, 2.0 * self.pitch, self.pitch


Mesh = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) float64 [m] and triangles (T, 3) int64 vertex indices


@dataclass(frozen=True, eq=False)
class World:
    """Static geometry in the world frame [m]: axis-aligned boxes, the ground square z = 0 and any other
    triangles (`extra_vertices`, `extra_triangles`: a mesh indexed from 0, appended after the rest)."""

    boxes: np.ndarray  # (K, 6) [xmin, ymin, zmin, xmax, ymax, zmax]
    ground: tuple[float, float, float, float]  # (xmin, ymin, xmax, ymax) of the ground square
    extra_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (V, 3) [m]
    extra_triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))  # (T, 3)

    def mesh(self) -> Mesh:
        """Triangle mesh of the world: vertices (V, 3) float64 [m] and triangles (T, 3) int64 indices."""
        bits = np.arange(8)
        lo, hi = self.boxes[:, :3], self.boxes[:, 3:]
        upper = np.stack([bits & 1, bits >> 1 & 1, bits >> 2 & 1], axis=1).astype(bool)  # (8, 3)
        corners = np.where(upper[None], hi[:, None, :], lo[:, None, :])  # (K, 8, 3)
        box_triangles = (_BOX_TRIANGLES[None] + 8 * np.arange(len(self.boxes))[:, None, None]).reshape(-1, 3)
        x0, y0, x1, y1 = self.ground
        ground_vertices = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x0, y1, 0.0], [x1, y1, 0.0]])
        ground_triangles = np.array([[0, 1, 2], [1, 3, 2]]) + 8 * len(self.boxes)
        vertices = np.concatenate([corners.reshape(-1, 3), ground_vertices, self.extra_vertices])
        extra_triangles = self.extra_triangles + 8 * len(self.boxes) + 4
        return vertices, np.concatenate([box_triangles, ground_triangles, extra_triangles])

    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        """An open3d raycasting scene holding the world mesh (float32 internally)."""
        return _scene(*self.mesh())

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [m] from (N, 3) world points to the nearest world surface (builds a scene)."""
        return _distance(self.raycasting_scene(), points)

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [m] from (N, 3) world points to the nearest surface that is not horizontal
        (walls, pillars, trunks, vehicles, crowns): the room around a sensor that `distance` hides under
        the ground, floors and ceilings (builds a scene)."""
        vertices, triangles = self.mesh()
        a, b, c = (vertices[triangles[:, k]] for k in range(3))
        normals = np.cross(b - a, c - a)
        upright = np.abs(normals[:, 2]) < 0.999 * np.linalg.norm(normals, axis=1)
        return _distance(_scene(vertices, triangles[upright]), points)


def _scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An open3d raycasting scene of one mesh: vertices (V, 3) [m], triangles (T, 3) indices."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene


def _distance(scene: o3d.t.geometry.RaycastingScene, points: np.ndarray) -> np.ndarray:
    """Unsigned distance [m] from (N, 3) points to the nearest triangle of `scene`."""
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def oriented_box(centre: Sequence[float], half_extents: Sequence[float], yaw: float = 0.0) -> Mesh:
    """A closed box: centre (x, y, z) [m], half extents along its own x, y, z [m], turned by `yaw` [rad]
    counter-clockwise about the world z axis. 8 vertices, 12 triangles wound outwards."""
    bits = np.arange(8)
    signs = np.stack([bits & 1, bits >> 1 & 1, bits >> 2 & 1], axis=1) * 2.0 - 1.0
    local = signs * np.asarray(half_extents, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rotation.T + np.asarray(centre, dtype=np.float64), _BOX_TRIANGLES.copy()


def cylinder(centre: Sequence[float], radius: float, bottom: float, top: float, sides: int = 10) -> Mesh:
    """A closed vertical prism of `sides` sides standing for a trunk, pillar or pole: axis through world
    (x, y) = centre [m], corners at `radius` [m], from z = bottom to z = top [m]. 4 * sides - 4 triangles."""
    angles = 2.0 * np.pi * np.arange(sides) / sides
    ring = np.asarray(centre, dtype=np.float64) + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    vertices = np.concatenate([np.column_stack([ring, np.full(sides, z)]) for z in (bottom, top)])
    k = np.arange(sides)
    after = (k + 1) % sides
    walls = np.concatenate([np.stack([k, after, k + sides], 1), np.stack([after, after + sides, k + sides], 1)])
    fan = np.arange(1, sides - 1)
    zero = np.zeros_like(fan)
    caps = np.concatenate([np.stack([zero, fan + 1, fan], 1), np.stack([zero, fan, fan + 1], 1) + sides])
    return vertices, np.concatenate([walls, caps])


def _unit_sphere() -> Mesh:
    """A unit sphere as an icosahedron with every edge halved and pushed out to the sphere: 42 vertices,
    80 triangles wound outwards."""
    g = 0.5 * (1.0 + np.sqrt(5.0))
    corners = np.array([[0.0, a, b * g] for a in (-1, 1) for b in (-1, 1)])
    corners = np.concatenate([np.roll(corners, shift, axis=1) for shift in range(3)])  # 12 corners, edges 2 long
    i, j = np.nonzero(np.triu(np.linalg.norm(corners[:, None] - corners[None], axis=2) < 2.1, k=1))
    vertices = np.concatenate([corners, corners[i] + corners[j]])
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    triangles = ConvexHull(vertices).simplices.astype(np.int64)
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a) < 0.0
    triangles[inward] = triangles[inward][:, ::-1]
    return vertices, triangles


_SPHERE_VERTICES, _SPHERE_TRIANGLES = _unit_sphere()


def ellipsoid(centre: Sequence[float], radii: Sequence[float]) -> Mesh:
    """A closed low-poly ellipsoid (a tree crown): centre (x, y, z) [m], semi-axes along world x, y, z [m].
    42 vertices, 80 triangles."""
    vertices = _SPHERE_VERTICES * np.asarray(radii, dtype=np.float64) + np.asarray(centre, dtype=np.float64)
    return vertices, _SPHERE_TRIANGLES.copy()


def merge_meshes(parts: Sequence[Mesh]) -> Mesh:
    """One mesh of all `parts` (each vertices (V, 3), triangles (T, 3) indexing its own vertices)."""
    offsets = np.cumsum([0] + [len(vertices) for vertices, _ in parts])
    vertices = np.concatenate([np.zeros((0, 3))] + [v for v, _ in parts])
    triangles = [np.zeros((0, 3), dtype=np.int64)] + [t + offset for (_, t), offset in zip(parts, offsets)]
    return vertices, np.concatenate(triangles).astype(np.int64)


def _side_box(
    side: int, size: float, along: tuple[float, float], outward: tuple[float, float], height: float
) -> list[float]:
    """Box [xmin, ymin, zmin, xmax, ymax, zmax] in block coordinates, placed against one block side.

    side: 0 south (y = 0), 1 north (y = size), 2 west (x = 0), 3 east (x = size). `along` runs along the
    side (x for south/north, y for west/east); `outward` is the signed distance from the side towards the
    street (negative: inside the block). All in metres.
    """
    o0, o1 = outward
    across = {0: (-o1, -o0), 1: (size + o0, size + o1), 2: (-o1, -o0), 3: (size + o0, size + o1)}[side]
    (x0, x1), (y0, y1) = (along, across) if side < 2 else (across, along)
    return [x0, y0, 0.0, x1, y1, height]


def _block_template(rng: np.random.Generator, size: float) -> np.ndarray:
    """Buildings of one block, (K, 6) boxes in block coordinates [0, size]^2: one row of identical units
    (same width, depth, height, gap) along each side."""
    depths = rng.uniform(9.0, 15.0, size=4)  # south, north, west, east
    boxes = []
    for side in range(4):
        width, gap, height = rng.uniform(8.0, 15.0), rng.uniform(1.5, 4.0), rng.uniform(6.0, 16.0)
        start, end = (0.0, size) if side < 2 else (depths[0] + gap, size - depths[1] - gap)
        count = max(1, int((end - start + gap) // (width + gap)))
        first = start + 0.5 * (end - start - count * width - (count - 1) * gap)
        for k in range(count):
            a = first + k * (width + gap)
            boxes.append(_side_box(side, size, (a, a + width), (-depths[side], 0.0), height))
    return np.array(boxes)


def _mirror(boxes: np.ndarray, size: float, axis: int) -> np.ndarray:
    """Reflect block-coordinate boxes across the block's centre line normal to `axis` (0: x, 1: y)."""
    mirrored = boxes.copy()
    mirrored[:, [axis, axis + 3]] = size - boxes[:, [axis + 3, axis]]
    return mirrored


def _vary_block(rng: np.random.Generator, boxes: np.ndarray, size: float) -> np.ndarray:
    """The template with this block's own changes: maybe one building re-heightened, a vacant lot, a
    courtyard tower that shows over the rows."""
    boxes = boxes.copy()
    if rng.random() < 0.5:
        k = rng.integers(len(boxes))
        boxes[k, 5] *= rng.choice([0.5, 1.7]) * rng.uniform(0.9, 1.1)
    if rng.random() < 0.3:
        boxes = np.delete(boxes, rng.integers(len(boxes)), axis=0)
    if rng.random() < 0.4:
        half = rng.uniform(4.0, 7.0, size=2)
        centre = rng.uniform(0.35 * size, 0.65 * size, size=2)
        tower = [*(centre - half), 0.0, *(centre + half), rng.uniform(25.0, 45.0)]
        boxes = np.vstack([boxes, tower])
    return boxes


def _floor_ledges(buildings: np.ndarray, floor_height: float = 3.5, protrusion: float = 0.4) -> np.ndarray:
    """Slabs 0.3 m thick protruding `protrusion` [m] around each building at every floor but the top:
    horizontal edges on the facades."""
    ledges = []
    for box in buildings:
        for z in np.arange(floor_height, box[5] - 1.0, floor_height):
            ledges.append([*(box[:2] - protrusion), z, *(box[3:5] + protrusion), z + 0.3])
    return np.array(ledges).reshape(-1, 6)


def _street_furniture(rng: np.random.Generator, size: float) -> np.ndarray:
    """Random, non-repeating clutter along one block's four sides, (K, 6) boxes in block coordinates.

    Distances are from the building line towards the street: low walls at 0.5 m, poles and trees (trunk
    and a box crown from 2.2-3.5 m up) at 1.5 m, parked cars at 3 m.
    """
    boxes = []
    for side in range(4):
        along = rng.uniform(0.0, 12.0)
        while along < size - 0.3:
            boxes.append(_side_box(side, size, (along, along + 0.3), (1.35, 1.65), rng.uniform(4.0, 8.0)))
            along += rng.uniform(12.0, 35.0)
        along = rng.uniform(1.0, 10.0)
        while along < size - 1.0:
            half, bottom = rng.uniform(0.9, 1.5), rng.uniform(2.2, 3.5)
            boxes.append(_side_box(side, size, (along - 0.2, along + 0.2), (1.3, 1.7), bottom))
            crown = _side_box(side, size, (along - half, along + half), (1.5 - half, 1.5 + half), 0.0)
            crown[2], crown[5] = bottom, bottom + rng.uniform(2.0, 4.0)
            boxes.append(crown)
            along += rng.uniform(8.0, 16.0)
        for start in rng.uniform(1.0, size - 5.5, size=rng.integers(0, 3)):
            boxes.append(_side_box(side, size, (start, start + 4.5), (2.05, 3.95), 1.5))
        if rng.random() < 0.25:
            start = rng.uniform(0.0, size - 6.0)
            end = min(size, start + rng.uniform(6.0, 20.0))
            boxes.append(_side_box(side, size, (start, end), (0.35, 0.65), rng.uniform(1.0, 2.5)))
    return np.array(boxes).reshape(-1, 6)


def build_city(seed: int, layout: CityLayout = CityLayout()) -> World:
    """The seeded city: the same block template in every block (mirrored by column and row parity),
    per-block changes, random street furniture, and a ground square reaching one pitch past the grid."""
    rng = np.random.default_rng(seed)
    size = layout.block_size
    template = _block_template(rng, size)
    boxes = []
    for i in range(layout.blocks_x):
        for j in range(layout.blocks_y):
            block = _mirror(template, size, 0) if i % 2 else template
            block = _mirror(block, size, 1) if j % 2 else block
            buildings = _vary_block(rng, block, size)
            block = np.vstack([buildings, _floor_ledges(buildings), _street_furniture(rng, size)])
            x0, y0 = layout.block_origin(i, j)
            boxes.append(block + [x0, y0, 0.0, x0, y0, 0.0])
    boxes = np.concatenate(boxes)
    p = layout.pitch
    return World(boxes=boxes, ground=(-2.0 * p, -2.0 * p, p * layout.blocks_x, p * layout.blocks_y))
