"""A spinning multi-beam LiDAR, simulated by ray casting with the sensor moving during the sweep."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import open3d as o3d


@dataclass(frozen=True)
class SpinningLidar:
    """Beams fanned in elevation, spun about the sensor's z axis once per `sweep_period`.

    Column k (k = 0 .. columns - 1) fires at time k * sweep_period / columns after the sweep starts, at
    azimuth pi - 2 pi k / columns: the sweep starts looking backwards and turns clockwise seen from above
    (left, forward, right), as Velodyne and Ouster sensors do. Every column is cast from the sensor pose at
    its own firing time. Beams are spread evenly in elevation. Sensor frame: x forward, y left, z up.
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

    def scan(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        T_world_sensor: np.ndarray,
        noise_sigma: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sweep, all rays cast in one call.

        Args:
            scene: the world, in the world frame.
            T_world_sensor: (columns, 4, 4) sensor pose at each column's firing time (`column_times`).
            noise_sigma: standard deviation of the Gaussian range noise [m] (needs `rng` when > 0).
            rng: source of the range noise.

        Returns:
            points (N, 3) float64 [m], each in the sensor frame at its own firing time (raw, not
            motion-compensated), ordered by time; and times (N,) [s] relative to the sweep start. Rays
            with no return within `max_range` are left out.
        """
        if T_world_sensor.shape != (self.columns, 4, 4):
            raise ValueError(f"T_world_sensor must be ({self.columns}, 4, 4), got {T_world_sensor.shape}")
        world_directions = np.einsum("cij,cbj->cbi", T_world_sensor[:, :3, :3], self.directions)
        origins = np.broadcast_to(T_world_sensor[:, None, :3, 3], world_directions.shape)
        rays = np.concatenate([origins, world_directions], axis=-1).astype(np.float32)
        ranges = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        hit = ranges <= self.max_range
        r = ranges[hit]
        if noise_sigma > 0.0:
            r = r + rng.normal(scale=noise_sigma, size=r.shape)
        points = r[:, None] * self.directions[hit]
        times = np.broadcast_to(self.column_times[:, None], hit.shape)[hit]
        return points, times
