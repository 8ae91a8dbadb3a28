"""Benchmark: wall-clock time to simulate one 1081-beam scan, at poses along a world's route."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from glassmap.sim.laser import LaserParams, cast_pairs, simulate_scan, _optics
from glassmap.sim.robot import RobotParams, compose
from glassmap.sim.world import World


@dataclass
class BenchResult:
    """Per-scan times in milliseconds over ``n`` scans (after warm-up)."""

    world: str
    n: int
    median_ms: float
    p90_ms: float
    mean_ms: float
    min_ms: float
    cast_median_ms: float
    mean_pairs: float
    segments: int = 0

    def summary(self) -> str:
        return (f"simulate_scan on '{self.world}': {self.n} scans, median {self.median_ms:.3f} ms, "
                f"p90 {self.p90_ms:.3f} ms, mean {self.mean_ms:.3f} ms, min {self.min_ms:.3f} ms "
                f"(ray casting alone: median {self.cast_median_ms:.3f} ms; "
                f"{self.mean_pairs:.0f} beam-segment pairs per scan, {self.segments} segments)")


def route_poses(world: World, n: int, route: str | None = None) -> np.ndarray:
    """(n, 3) laser poses (map frame) spread evenly along a route, heading along each leg."""
    wp = world.route(route)
    legs = np.diff(wp, axis=0)
    lens = np.hypot(legs[:, 0], legs[:, 1])
    s = np.linspace(0, lens.sum(), n, endpoint=False)
    leg = np.minimum(np.searchsorted(np.cumsum(lens), s, side="right"), len(legs) - 1)
    frac = (s - (np.cumsum(lens) - lens)[leg]) / lens[leg]
    xy = wp[leg] + frac[:, None] * legs[leg]
    yaw = np.arctan2(legs[leg, 1], legs[leg, 0])
    base = np.column_stack([xy, yaw])
    return compose(base, np.asarray(RobotParams().laser_offset))


def bench_scan(world: World, n: int = 400, warmup: int = 40, seed: int = 0,
               params: LaserParams = LaserParams()) -> BenchResult:
    """Time ``simulate_scan`` at ``n`` poses along the world's default route (single process)."""
    rng = np.random.default_rng(seed)
    poses = route_poses(world, n)
    for p in poses[:warmup]:
        simulate_scan(world, p, rng, params)
    times = np.empty(n)
    cast = np.empty(n)
    pairs = np.empty(n)
    opt = _optics(world, params)
    for i, p in enumerate(poses):
        t0 = time.perf_counter()
        simulate_scan(world, p, rng, params)
        t1 = time.perf_counter()
        b = cast_pairs(world, p, max_range=params.max_reading, optics=opt)[0]
        t2 = time.perf_counter()
        times[i], cast[i], pairs[i] = t1 - t0, t2 - t1, b.size
    ms = times * 1e3
    return BenchResult(world=world.name, n=n, median_ms=float(np.median(ms)), p90_ms=float(np.percentile(ms, 90)),
                       mean_ms=float(ms.mean()), min_ms=float(ms.min()), cast_median_ms=float(np.median(cast) * 1e3),
                       mean_pairs=float(pairs.mean()), segments=len(world.segments))
