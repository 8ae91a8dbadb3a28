"""Synthetic scans from a few line segments (no simulator needed): exact ray casting, vectorized."""

from __future__ import annotations

import numpy as np

from glassmap.types import LaserGeometry, Scan


def raycast(segments: np.ndarray, laser_pose: np.ndarray, angles: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """Range (m) along each beam to the nearest segment; +inf when nothing is hit within max_range.

    segments: (m, 4) as (x1, y1, x2, y2), map frame; laser_pose (3,) map frame; angles (n,) laser frame.
    """
    seg = np.asarray(segments, dtype=np.float64)
    a = laser_pose[2] + np.asarray(angles)
    d = np.stack([np.cos(a), np.sin(a)], axis=1)  # (n, 2)
    p = laser_pose[:2]
    s0, e = seg[:, :2], seg[:, 2:] - seg[:, :2]  # (m, 2)
    denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (n, m)
    w = s0[None, :, :] - p  # (1, m, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    t = np.where(hit, t, np.inf).min(axis=1)
    return np.where(t <= max_range, t, np.inf)


def box(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Four segments of an axis-aligned rectangle."""
    return np.array([[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]], dtype=np.float64)


def corridor(length: float = 40.0, half_width: float = 1.0) -> np.ndarray:
    """Two long parallel walls along x (no ends within reach of the tests' laser range)."""
    return np.array([[-length / 2, -half_width, length / 2, -half_width],
                     [-length / 2, half_width, length / 2, half_width]], dtype=np.float64)


def room_with_corner() -> np.ndarray:
    """A 6 x 4 m room with a pillar: rich geometry in every direction."""
    return np.concatenate([box(-3.0, -2.0, 3.0, 2.0), box(1.0, 0.5, 1.5, 1.0)])


def make_scan(segments: np.ndarray, laser_pose: np.ndarray, stamp: float = 0.0, noise: float = 0.0,
              rng: np.random.Generator | None = None, geometry: LaserGeometry = LaserGeometry()) -> Scan:
    r = raycast(segments, np.asarray(laser_pose, dtype=np.float64), geometry.angles, geometry.range_max)
    if noise > 0:
        rng = rng or np.random.default_rng(0)
        r = r + rng.normal(0.0, noise, r.shape)
    return Scan(stamp=stamp, ranges=r, intensities=None, geometry=geometry)
