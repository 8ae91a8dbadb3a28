"""Deterministic scans and odometry for the runtime tests."""

from __future__ import annotations

import numpy as np

from glassmap.types import LaserGeometry, Odometry, Scan


def make_scan(stamp: float, seq: int = 0, n: int = 1081) -> Scan:
    """A deterministic scan whose values encode seq (ranges 1..5 m, intensities 100 + seq)."""
    ranges = np.linspace(1.0, 5.0, n) + 0.001 * seq
    ranges[::97] = np.nan
    ranges[5] = np.inf
    return Scan(stamp=stamp, ranges=ranges, intensities=np.full(n, 100.0 + seq),
                geometry=LaserGeometry(n_beams=n), seq=seq)


def make_odom(stamp: float, x: float = 0.0) -> Odometry:
    return Odometry(stamp=stamp, x=x, y=0.5 * x, yaw=0.1 * x, v=0.3, omega=0.05,
                    covariance=np.diag([1e-4, 2e-4, 3e-5]) * (1 + x))
