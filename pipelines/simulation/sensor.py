"""Simulated LiDARs: spinning multi-beam sensors and non-repetitive (Livox-like) ones, ray cast with the sensor
moving during the sweep.

Every sensor fires in bursts: firing k of a sweep emits a few rays at once (one per beam or laser line) at time
`firing_times(sweep)[k]` after the sweep start, and is cast from the sensor pose at that time. Sensor frame: x
forward, y left, z up. `PRESETS` names sensors modelled on common ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np
import open3d as o3d


class Lidar(Protocol):
    """What `SimulatedSequence` needs of a sensor."""

    @property
    def sweep_period(self) -> float:
        """Duration of one sweep [s]; sweeps follow each other without gap."""

    @property
    def max_range(self) -> float:
        """Farthest return kept [m]."""

    def firing_times(self, sweep: int) -> np.ndarray:
        """(C,) firing times [s] of sweep `sweep`, relative to its start, increasing, in [0, sweep_period)."""

    def scan(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        T_world_sensor: np.ndarray,
        sweep: int = 0,
        noise_sigma: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sweep `sweep` cast in `scene` (world frame) from T_world_sensor (C, 4, 4), the sensor pose at each of
        `firing_times(sweep)`; Gaussian range noise of `noise_sigma` [m] drawn from `rng` (needed when > 0).

        Returns points (N, 3) float64 [m], each in the sensor frame at its own firing time (raw, not motion
        compensated), ordered by time; and their times (N,) [s] relative to the sweep start. Rays with no return
        within the sensor's range are left out.
        """


@dataclass(frozen=True)
class SpinningLidar:
    """Beams fanned in elevation, spun about the sensor's z axis once per `sweep_period`.

    Column k (k = 0 .. columns - 1) fires at time k * sweep_period / columns after the sweep starts, at
    azimuth pi - 2 pi k / columns: the sweep starts looking backwards and turns clockwise seen from above
    (left, forward, right), as Velodyne and Ouster sensors do. Every column is cast from the sensor pose at
    its own firing time. Beams are spread evenly in elevation. The same pattern repeats every sweep.
    """

    beams: int = 32
    elevation_min_deg: float = -25.0
    elevation_max_deg: float = 15.0
    columns: int = 900
    max_range: float = 100.0  # [m]; farther returns are dropped
    sweep_period: float = 0.1  # [s]

    @cached_property
    def column_times(self) -> np.ndarray:
        """(columns,) firing time of each column [s] relative to the sweep start, in [0, sweep_period)."""
        return np.arange(self.columns) * (self.sweep_period / self.columns)

    @cached_property
    def directions(self) -> np.ndarray:
        """(columns, beams, 3) unit ray directions in the sensor frame."""
        azimuth = np.pi - 2.0 * np.pi * np.arange(self.columns) / self.columns
        elevation = np.deg2rad(np.linspace(self.elevation_min_deg, self.elevation_max_deg, self.beams))
        a, e = np.meshgrid(azimuth, elevation, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)

    def firing_times(self, sweep: int) -> np.ndarray:
        """(columns,) `column_times`, the same for every sweep."""
        return self.column_times

    def scan(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        T_world_sensor: np.ndarray,
        sweep: int = 0,
        noise_sigma: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sweep, all rays cast in one call; see `Lidar.scan` (T_world_sensor: (columns, 4, 4))."""
        return _cast(scene, T_world_sensor, self.directions, self.column_times, 0.0, self.max_range, noise_sigma, rng)


class _LaserLines:
    """What the non-repetitive sensors share: `rays_per_sweep` rays a sweep from `lines` lasers firing together
    at evenly spaced times, in directions that change from sweep to sweep (`ray_directions`), returns kept in
    [`min_range`, `max_range`]."""

    rays_per_sweep: int
    lines: int
    min_range: float
    max_range: float
    sweep_period: float

    def __post_init__(self) -> None:
        if self.rays_per_sweep % self.lines:
            raise ValueError(f"rays_per_sweep {self.rays_per_sweep} is not a multiple of lines {self.lines}")

    @property
    def firings(self) -> int:
        """Firings per sweep."""
        return self.rays_per_sweep // self.lines

    def firing_times(self, sweep: int) -> np.ndarray:
        """(firings,) firing times [s] relative to the sweep start, evenly spaced, the same for every sweep."""
        return np.arange(self.firings) * (self.sweep_period / self.firings)

    def ray_directions(self, sweep: int) -> np.ndarray:
        """(firings, lines, 3) unit ray directions of sweep `sweep` in the sensor frame."""
        raise NotImplementedError

    def scan(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        T_world_sensor: np.ndarray,
        sweep: int = 0,
        noise_sigma: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sweep, all rays cast in one call; see `Lidar.scan` (T_world_sensor: (firings, 4, 4))."""
        directions, times = self.ray_directions(sweep), self.firing_times(sweep)
        return _cast(scene, T_world_sensor, directions, times, self.min_range, self.max_range, noise_sigma, rng)


@dataclass(frozen=True)
class RosetteLidar(_LaserLines):
    """A forward-looking sensor with a non-repetitive rosette pattern, like a Livox Avia or Mid-40.

    Two wedge prisms spinning in opposite directions at incommensurate rates (`prism_hz`) deflect the beam by
    the sum of two equal circular motions: a rosette whose petals all pass through the centre and precess from
    petal to petal, so the pattern never repeats and fills the field of view more the longer it is watched
    (denser at its centre). `lines` lasers fire together through the prisms, offset from each other by
    `line_spacing_deg` vertically. All rays lie within `fov_deg` / 2 of the sensor's x axis.

    Firing k of sweep s fires at t_k = k * sweep_period / firings after the sweep start and follows the pattern
    at time s * sweep_period + t_k: the pattern runs on across sweeps.
    """

    fov_deg: float = 70.4  # full angle of the circular field of view [deg]
    rays_per_sweep: int = 24_000  # a multiple of `lines`
    lines: int = 6
    line_spacing_deg: float = 0.8
    prism_hz: tuple[float, float] = (131.0, 131.0 * 0.5 * (5.0**0.5 - 1.0))  # [Hz], counter-rotating
    max_range: float = 200.0  # [m]
    min_range: float = 1.0  # [m]; nearer returns are dropped
    sweep_period: float = 0.1  # [s]

    def ray_directions(self, sweep: int) -> np.ndarray:
        """(firings, lines, 3) unit ray directions of sweep `sweep` in the sensor frame."""
        offsets = np.deg2rad(self.line_spacing_deg) * (np.arange(self.lines) - 0.5 * (self.lines - 1))
        radius = 0.5 * np.deg2rad(self.fov_deg) - np.abs(offsets).max()  # reach of the rosette [rad]
        cycles = np.outer(sweep * self.sweep_period + self.firing_times(sweep), self.prism_hz)  # (firings, 2)
        turns = np.exp(2j * np.pi * np.mod(cycles, 1.0))
        deflection = 0.5 * radius * (turns[:, 0] + turns[:, 1].conj())  # counter-rotating; (left, up) as y + i z
        return _deflected(deflection[:, None] + 1j * offsets)


@dataclass(frozen=True)
class ZigzagLidar(_LaserLines):
    """An all-round sensor with a non-repetitive pattern, like a Livox Mid-360: the head spins about z once per
    sweep (starting backwards, clockwise seen from above, as `SpinningLidar`) while the beam's elevation sweeps
    up and down between `elevation_min_deg` and `elevation_max_deg` at `oscillation_hz`, a triangle wave
    (uniform in elevation) incommensurate with the spin, so every sweep zigzags through other elevations.
    `lines` lasers fire together, `line_spacing_deg` apart in elevation, all within the elevation limits.

    Firing k of sweep s fires at t_k = k * sweep_period / firings after the sweep start; the oscillation runs on
    across sweeps (its phase at t_k is oscillation_hz * (s * sweep_period + t_k) cycles).
    """

    elevation_min_deg: float = -7.0
    elevation_max_deg: float = 52.0
    rays_per_sweep: int = 20_000  # a multiple of `lines`
    lines: int = 4
    line_spacing_deg: float = 0.6
    oscillation_hz: float = 1006.18034  # 100 + 1 / golden ratio oscillations per 0.1 s sweep
    max_range: float = 70.0  # [m]
    min_range: float = 0.1  # [m]; nearer returns are dropped
    sweep_period: float = 0.1  # [s]

    def ray_directions(self, sweep: int) -> np.ndarray:
        """(firings, lines, 3) unit ray directions of sweep `sweep` in the sensor frame."""
        times = self.firing_times(sweep)
        azimuth = np.pi - 2.0 * np.pi * times / self.sweep_period
        phase = np.mod(self.oscillation_hz * (sweep * self.sweep_period + times), 1.0)
        triangle = np.abs(2.0 * phase - 1.0)  # 1 -> 0 -> 1 over one oscillation
        offsets = self.line_spacing_deg * (np.arange(self.lines) - 0.5 * (self.lines - 1))
        low, high = self.elevation_min_deg - offsets.min(), self.elevation_max_deg - offsets.max()
        elevation = np.deg2rad(low + (high - low) * triangle[:, None] + offsets)  # (firings, lines)
        a = azimuth[:, None]
        return np.stack([np.cos(elevation) * np.cos(a), np.cos(elevation) * np.sin(a), np.sin(elevation)], axis=-1)


def _deflected(angles: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) deflected from the x axis by `angles` (...) complex [rad]: real part towards y
    (left), imaginary towards z (up); the direction makes angle |angles| with the x axis."""
    tilt = np.abs(angles)
    toward = np.sinc(tilt / np.pi) * angles  # sin(tilt) along the deflection, exact at tilt 0
    return np.stack([np.cos(tilt), toward.real, toward.imag], axis=-1)


def _cast(
    scene: o3d.t.geometry.RaycastingScene,
    T_world_sensor: np.ndarray,
    directions: np.ndarray,
    times: np.ndarray,
    min_range: float,
    max_range: float,
    noise_sigma: float,
    rng: np.random.Generator | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Cast the rays `directions` (C, L, 3) (sensor frame) of C firings at `times` (C,) [s] from T_world_sensor
    (C, 4, 4); keep returns in [min_range, max_range] [m], add range noise; see `Lidar.scan`."""
    if T_world_sensor.shape != (len(times), 4, 4):
        raise ValueError(f"T_world_sensor must be ({len(times)}, 4, 4), got {T_world_sensor.shape}")
    world_directions = np.einsum("cij,cbj->cbi", T_world_sensor[:, :3, :3], directions)
    origins = np.broadcast_to(T_world_sensor[:, None, :3, 3], world_directions.shape)
    rays = np.concatenate([origins, world_directions], axis=-1).astype(np.float32)
    ranges = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    hit = (ranges >= min_range) & (ranges <= max_range)
    r = ranges[hit]
    if noise_sigma > 0.0:
        r = r + rng.normal(scale=noise_sigma, size=r.shape)
    points = r[:, None] * directions[hit]
    return points, np.broadcast_to(times[:, None], hit.shape)[hit]


VLP16_LIKE = SpinningLidar(beams=16, elevation_min_deg=-15.0, elevation_max_deg=15.0, columns=1800)
SPINNING_32 = SpinningLidar()  # the default of `simulate_sequence`
OS128_LIKE = SpinningLidar(beams=128, elevation_min_deg=-22.5, elevation_max_deg=22.5, columns=1024, max_range=120.0)
AVIA_LIKE = RosetteLidar()
MID360_LIKE = ZigzagLidar()
PRESETS: dict[str, Lidar] = {
    "vlp16": VLP16_LIKE,
    "spinning32": SPINNING_32,
    "os128": OS128_LIKE,
    "avia": AVIA_LIKE,
    "mid360": MID360_LIKE,
}
