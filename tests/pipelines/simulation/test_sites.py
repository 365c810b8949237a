"""The simulated sites: the box city unchanged, seeded worlds, drivable paths clear of obstacles, closed indoors."""

import hashlib

import numpy as np
import open3d as o3d
import pytest

from pipelines.simulation.sites import (
    CLEARANCE,
    INDOOR_CLEARANCE,
    ROAD_CLEARANCE,
    Site,
    build_campus,
    build_city_site,
    build_garage,
    build_office,
)
from pipelines.simulation.world import CityLayout, World, build_city, cylinder, ellipsoid, merge_meshes, oriented_box

BUILDERS = {"city": build_city_site, "garage": build_garage, "campus": build_campus, "office": build_office}
MARGINS = {("campus", "loop"): ROAD_CLEARANCE, ("campus", "out_and_back"): ROAD_CLEARANCE}  # else CLEARANCE
LAP_LENGTHS = {  # [m]
    ("garage", "loop"): (200, 300),
    ("campus", "loop"): (500, 700),
    ("campus", "walk"): (200, 300),
    ("office", "loop"): (100, 150),
}


@pytest.fixture(scope="module")
def sites() -> dict[str, Site]:
    return {name: build(0) for name, build in BUILDERS.items()}


def sample(path: np.ndarray, step: float = 0.5) -> np.ndarray:
    """Points at most `step` [m] apart along the straight segments of a path, waypoints included."""
    pieces = []
    for a, b in zip(path[:-1], path[1:]):
        count = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
        pieces.append(a + np.linspace(0.0, 1.0, count)[:, None] * (b - a))
    return np.concatenate(pieces)


def margin(site: str, path: str) -> float:
    """The clearance [m] a path keeps from obstacles."""
    return INDOOR_CLEARANCE if site == "office" else MARGINS.get((site, path), CLEARANCE)


def rounded(path: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The path's corners rounded by arcs of `radius` [m] tangent to both segments: per segment the length
    [m] its corners take from it, and points (M, 2) along the arcs."""
    closed = np.array_equal(path[0], path[-1])
    points = path[:-1] if closed else path
    taken, arcs = np.zeros(len(path) - 1), []
    for k in range(0, len(points)) if closed else range(1, len(points) - 1):
        a, b, c = points[k - 1], points[k], points[(k + 1) % len(points)]
        u, v = (b - a) / np.linalg.norm(b - a), (c - b) / np.linalg.norm(c - b)
        turn = np.arctan2(u[0] * v[1] - u[1] * v[0], u @ v)
        tangent = radius * np.tan(abs(turn) / 2)
        taken[k - 1] += tangent
        taken[k % len(taken)] += tangent
        centre = b - tangent * u + radius * np.sign(turn) * np.array([-u[1], u[0]])
        start = np.arctan2(*(b - tangent * u - centre)[::-1])
        angles = start + np.linspace(0.0, turn, 16)
        arcs.append(centre + radius * np.column_stack([np.cos(angles), np.sin(angles)]))
    return taken, np.concatenate(arcs)


def test_city_mesh_is_unchanged():
    """SHA-256 of the city's mesh (seeds 0 and 1) as it was before `World` held other triangles."""
    expected = {
        0: "f0ca2b64f5bc19354ecb3ed0ccb9bf12bfbc2f6879226c5c8d772d897152db69",
        1: "370dc692305d6242e7ea041e1cca63cb5b5b1a94f3a5388d1c44a7ae99fb0920",
    }
    for seed, digest in expected.items():
        vertices, triangles = build_city(seed).mesh()
        assert vertices.dtype == np.float64 and triangles.dtype == np.int64
        assert hashlib.sha256(vertices.tobytes() + triangles.tobytes()).hexdigest() == digest
    site = build_city_site(0)
    np.testing.assert_array_equal(site.world.mesh()[0], build_city(0).mesh()[0])
    x0, y0, x1, y1 = CityLayout().loop
    np.testing.assert_array_equal(site.paths["loop"], [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])


def test_parts_are_closed_and_appended_after_the_boxes():
    box = oriented_box([10.0, 0.0, 1.0], [2.0, 0.5, 1.0], yaw=np.pi / 2)
    np.testing.assert_allclose(box[0].min(axis=0), [9.5, -2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(box[0].max(axis=0), [10.5, 2.0, 2.0], atol=1e-12)
    pole = cylinder([0.0, 10.0], 0.3, 0.0, 4.0, sides=10)
    crown = ellipsoid([0.0, 10.0, 5.0], [2.0, 2.0, 1.5])
    assert len(pole[1]) == 36 and (len(crown[0]), len(crown[1])) == (42, 80)
    np.testing.assert_allclose(np.linalg.norm(pole[0][:, :2] - [0.0, 10.0], axis=1), 0.3)
    np.testing.assert_allclose(np.linalg.norm((crown[0] - [0.0, 10.0, 5.0]) / [2.0, 2.0, 1.5], axis=1), 1.0)
    for _, triangles in (box, pole, crown):
        edges = {tuple(edge) for k in range(3) for edge in triangles[:, [k, (k + 1) % 3]]}
        assert len(edges) == 3 * len(triangles) and all((b, a) in edges for a, b in edges)  # closed, one winding
    parts = merge_meshes([box, pole, crown])
    city = build_city(0)
    world = World(city.boxes, city.ground, *parts)
    (vertices, triangles), (city_vertices, city_triangles) = world.mesh(), city.mesh()
    np.testing.assert_array_equal(vertices, np.concatenate([city_vertices, box[0], pole[0], crown[0]]))
    offsets = len(city_vertices) + np.array([0, 8, 28])
    expected = [city_triangles, box[1] + offsets[0], pole[1] + offsets[1], crown[1] + offsets[2]]
    np.testing.assert_array_equal(triangles, np.concatenate(expected))
    point = np.array([[0.0, 14.0, 5.0]])  # 2 m beside the crown, 5 m above the ground
    assert World(np.zeros((0, 6)), (-50.0, -50.0, 50.0, 50.0), *parts).distance(point)[0] == pytest.approx(2.0, abs=0.1)
    lawn = World(np.zeros((0, 6)), (-50.0, -50.0, 50.0, 50.0), *box)
    low = np.array([[0.0, 0.0, 0.3]])
    assert lawn.distance(low)[0] == pytest.approx(0.3) and lawn.clearance(low)[0] == pytest.approx(9.5)


@pytest.mark.parametrize("name", BUILDERS)
def test_sites_are_seeded(name):
    build = BUILDERS[name]
    a, b, c = build(3), build(3), build(4)
    for x, y in zip(a.world.mesh(), b.world.mesh()):
        np.testing.assert_array_equal(x, y)
    assert a.paths.keys() == b.paths.keys()
    for key, path in a.paths.items():
        np.testing.assert_array_equal(path, b.paths[key])
    vertices, other = a.world.mesh()[0], c.world.mesh()[0]
    assert vertices.shape != other.shape or not np.array_equal(vertices, other)


@pytest.mark.parametrize("name", BUILDERS)
def test_paths_are_drivable(sites, name):
    """No turn over 150 degrees; loops closed; "out_and_back" open and leaving along the way it comes back
    on; lap lengths as specified."""
    for key, path in sites[name].paths.items():
        assert path.ndim == 2 and path.shape[1] == 2 and path.dtype == np.float64
        steps = np.diff(path, axis=0)
        closed = np.array_equal(path[0], path[-1])
        assert closed == (key != "out_and_back"), key
        headings = np.arctan2(steps[:, 1], steps[:, 0])
        headings = np.append(headings, headings[0]) if closed else headings
        assert np.abs(np.angle(np.exp(1j * np.diff(headings)))).max() <= np.deg2rad(150.0), key
        if not closed:
            out, back = steps[0] / np.linalg.norm(steps[0]), steps[-1] / np.linalg.norm(steps[-1])
            np.testing.assert_allclose(back, -out, atol=1e-12)
            aside = path[-1] - path[0]
            assert abs(out[0] * aside[1] - out[1] * aside[0]) < 1e-9  # it ends on the line it left along
        if (name, key) in LAP_LENGTHS:
            low, high = LAP_LENGTHS[name, key]
            assert low <= np.linalg.norm(steps, axis=1).sum() <= high, key


@pytest.mark.parametrize("name", BUILDERS)
def test_paths_keep_clear_of_obstacles(sites, name):
    """Every 0.5 m along every path, 0.3 m and 1.5 m up, walls, pillars, trunks, crowns and cars are
    beyond the margin (floors, ceilings and the ground, horizontal, do not count)."""
    site = sites[name]
    for key, path in site.paths.items():
        xy = sample(path)
        for height in (0.3, 1.5):
            clearance = site.world.clearance(np.column_stack([xy, np.full(len(xy), height)]))
            assert clearance.min() >= margin(name, key), (key, height, xy[np.argmin(clearance)])
        above = site.world.distance(np.column_stack([xy, np.full(len(xy), 1.5)]))
        assert above.min() >= min(margin(name, key), 1.4), key  # nothing overhead either: ceilings are 3 m up


@pytest.mark.parametrize("name", BUILDERS)
def test_rounded_corners_fit_and_keep_clear(sites, name):
    """Rounded by arcs of 6 m (driving) or 1.5 m (walking), every corner fits in its segments and the arcs
    keep the path's margin."""
    site = sites[name]
    for key, path in site.paths.items():
        taken, arcs = rounded(path, 1.5 if name == "office" or key == "walk" else 6.0)
        assert np.all(taken <= np.linalg.norm(np.diff(path, axis=0), axis=1)), key
        for height in (0.3, 1.5):
            clearance = site.world.clearance(np.column_stack([arcs, np.full(len(arcs), height)]))
            assert clearance.min() >= margin(name, key), (key, height, arcs[np.argmin(clearance)])


@pytest.mark.parametrize("name", ["garage", "office"])
def test_indoors_rays_hit_within_100_m(sites, name):
    site = sites[name]
    scene = site.world.raycasting_scene()
    directions = np.random.default_rng(0).standard_normal((200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for path in site.paths.values():
        origin = np.array([*path[1], 1.5])
        rays = np.column_stack([np.broadcast_to(origin, directions.shape), directions]).astype(np.float32)
        hits = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        assert np.mean(hits <= 100.0) >= 0.95


def test_garage_pillars_repeat_every_8_m(sites):
    """Looking north from the y = 13 lane, 2.3 m up (over the cars), the pillar row at y = 19 shows one
    pillar every 8 m, all alike."""
    x = np.arange(6.0, 94.0, 0.25)
    rays = np.column_stack([x, np.full_like(x, 13.0), np.full_like(x, 2.3), np.zeros_like(x), np.ones_like(x), 0 * x])
    hits = sites["garage"].world.raycasting_scene().cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"]
    pillar = hits.numpy() < 6.0  # the pillar faces are 5.7 m away, anything else in the strip beyond 6.5 m
    spacing = (x[pillar] - 10.0) / 8.0
    assert np.all(np.abs(spacing - np.round(spacing)) * 8.0 <= 0.3)
    assert set(np.round(spacing).astype(int)) == set(range(11))
    np.testing.assert_allclose(hits.numpy()[pillar], 5.7, atol=1e-4)
