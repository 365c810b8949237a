"""What every source of LiDAR points shares (PointCloud2 messages, PCD/PLY files): which points are returns, and the
conventions of per-point time fields."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

TIME_FIELDS = ("t", "time", "timestamp", "time_offset", "offset_time")  # searched in this order


def time_field(names: Iterable[str]) -> str | None:
    """The first of `TIME_FIELDS` among a cloud's field names, or None."""
    names = set(names)
    return next((name for name in TIME_FIELDS if name in names), None)


def carries_livox_tags(names: Iterable[str], tag_is_uint8: bool) -> bool:
    """Whether a cloud's fields are those of a Livox driver (livox_ros_driver(2)'s PointCloud2, the PCD files written
    from it): a uint8 `tag` beside a `line` field. Another driver's `tag` is not read as Livox's."""
    names = set(names)
    return tag_is_uint8 and "tag" in names and "line" in names


def returns(points: np.ndarray, livox_tags: np.ndarray | None = None) -> np.ndarray | None:
    """Mask of the (N, 3) points that are returns: finite, not exactly at the origin (the no-return points of
    Ouster drivers), and, given Livox tags (N,), not tagged as noise (`livox_noise`); None when every point is one."""
    squared_range = np.einsum("ij,ij->i", points, points)  # NaN or inf unless x, y and z are all finite
    valid = (squared_range > 0.0) & (squared_range < np.inf)
    if livox_tags is not None:
        valid &= ~livox_noise(livox_tags)
    return None if valid.all() else valid


def livox_noise(tags: np.ndarray) -> np.ndarray:
    """Mask of the points a Livox sensor tags (uint8, one a point) as noise with high confidence: the point property
    from the spatial position (bits 0-1) or from the intensity (bits 2-3) is 01 (dust, rain, fog), or the Mid-70's
    nearby-waveform distortion (bits 6-7) is 01. Moderate and low confidence (10, 11) and the return number (bits
    4-5) keep the point."""
    tags = np.asarray(tags).astype(np.uint8, copy=False)
    return ((tags & 0x03) == 0x01) | ((tags & 0x0C) == 0x04) | ((tags & 0xC0) == 0x40)


def relative_seconds(values: np.ndarray, stamp: float) -> np.ndarray:
    """Per-point times [s] relative to the cloud's `stamp` [s] from the raw values of its time field.

    - Unit: integer fields are nanoseconds (Ouster `t` uint32, Livox `offset_time` uint32); float fields are seconds
      (Velodyne `time` float32, Hesai/Robosense `timestamp` float64), unless their typical magnitude exceeds 1e12:
      then nanoseconds (the float64 `timestamp` of Livox's driver2 PointCloud2).
    - Reference: the values are absolute times when their median is beyond 1 s and closer to the stamp than to zero
      (the stamp is then subtracted); relative to the stamp otherwise.
    - A field with the same value at every point (or any non-finite value) carries no time: an empty array.
    """
    values = np.asarray(values).reshape(-1)
    if values.size == 0 or not np.isfinite(values).all():
        return np.empty(0)
    typical = float(np.median(values[:: max(1, values.size // 256)]))
    scale = 1e-9 if values.dtype.kind in "iu" or abs(typical) > 1e12 else 1.0
    times = values.astype(np.float64) * scale
    if abs(typical * scale) > 1.0 and abs(typical * scale - stamp) < abs(typical * scale):
        times -= stamp  # absolute times
    if times.min() == times.max():
        return np.empty(0)
    return times


def nanoseconds_after_stamp(times: np.ndarray, count: int) -> np.ndarray:
    """Per-point times [s] after a cloud's stamp as the integer nanoseconds of uint32 time fields (Ouster `t`, Livox
    `offset_time`), for a cloud of `count` points; zeros when `times` is empty.

    Raises:
        ValueError: not one time per point, or a time outside [0, 4.29) s.
    """
    times = np.asarray(times, dtype=np.float64)
    if not len(times):
        return np.zeros(count, dtype=np.uint32)
    if len(times) != count or times.min() < 0 or times.max() >= 2**32 * 1e-9:
        raise ValueError("times must be one per point, within [0, 4.29) s of the stamp")
    return np.round(times * 1e9).astype(np.uint32)
