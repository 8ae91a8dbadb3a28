"""Compiled per-beam loops of :mod:`glassmap.pose.estimator`, numba ``njit``.

Each kernel does the floating-point operations of the numpy code it replaced in the same order (no
fast-math; float32 stays float32), so its output is the same to the last bit; the cosines and sines of the
beams stay in numpy. End points (n, 2) are map-frame (m); a grid cell of an end point is
``floor((p - origin) / res)`` per axis (as ``MapGrid.world_to_cell``), points off the (h, w) grid are
skipped. Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def registration_sigmas(ranges: np.ndarray, sxy2: float, sth2: float, range_sigma: float,
                        range_sigma_per_m: float) -> np.ndarray:
    """sqrt(sxy2 + r^2 sth2 + (range_sigma + range_sigma_per_m r)^2) per beam (m); NaN where r is not finite."""
    n = ranges.shape[0]
    out = np.empty(n, np.float64)
    for i in range(n):
        r = ranges[i]
        if np.isfinite(r):
            sr = range_sigma + range_sigma_per_m * r
            out[i] = np.sqrt(sxy2 + r * r * sth2 + sr * sr)
        else:
            out[i] = np.nan
    return out


@_jit
def add_hits(sx: np.ndarray, sy: np.ndarray, count: np.ndarray, key: np.ndarray, key_value: np.float32,
             end: np.ndarray, ox: float, oy: float, res: float) -> None:
    """Add each end point's offset from its cell's corner (m, float32) to ``sx``, ``sy``, 1 to ``count`` and
    ``key_value`` to ``key`` ((h, w) float32 layers; ``key`` may be empty (0, 0): none), in the order of the
    points."""
    h, w = count.shape
    with_key = key.size > 0
    for i in range(end.shape[0]):
        ix = np.int64(np.floor((end[i, 0] - ox) / res))
        iy = np.int64(np.floor((end[i, 1] - oy) / res))
        if ix < 0 or ix >= w or iy < 0 or iy >= h:
            continue
        sx[iy, ix] += np.float32(end[i, 0] - (ox + ix * res))
        sy[iy, ix] += np.float32(end[i, 1] - (oy + iy * res))
        count[iy, ix] += np.float32(1.0)
        if with_key:
            key[iy, ix] += key_value


@_jit
def mean_keys(key: np.ndarray, count: np.ndarray, xy: np.ndarray, ox: float, oy: float, res: float) -> np.ndarray:
    """For each map-frame point of ``xy`` (n, 2) whose cell lies in the (h, w) float32 layers and holds end
    points (``count`` > 0), in order: ``key / count`` rounded (float32 floor(key / count + 0.5)), int32."""
    h, w = count.shape
    out = np.empty(xy.shape[0], np.int32)
    m = 0
    half = np.float32(0.5)
    for i in range(xy.shape[0]):
        ix = np.int64(np.floor((xy[i, 0] - ox) / res))
        iy = np.int64(np.floor((xy[i, 1] - oy) / res))
        if ix < 0 or ix >= w or iy < 0 or iy >= h:
            continue
        n = count[iy, ix]
        if n > 0:
            out[m] = np.int32(np.floor(key[iy, ix] / n + half))
            m += 1
    return out[:m]


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) these kernels now, with the argument types the
    estimator passes, rather than at the first scan."""
    lay = [np.zeros((2, 2), np.float32) for _ in range(3)]
    end = np.zeros((1, 2))
    registration_sigmas(np.zeros(1), 0.0, 0.0, 0.0, 0.0)
    add_hits(lay[0], lay[1], lay[2], lay[0], np.float32(0.0), end, 0.0, 0.0, 1.0)
    mean_keys(lay[0], lay[1], end, 0.0, 0.0, 1.0)
    one = np.zeros(1)
    seen_through_glass(lay[0], 0.0, 0.0, 1.0, 0.0, 0.0, one, one, one, one)


@_jit
def seen_through_glass(glass: np.ndarray, ox: float, oy: float, res: float, lx: float, ly: float, ux: np.ndarray,
                       uy: np.ndarray, reach: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Per beam (n,): whether a sample of its path from the laser at (lx, ly) along (ux, uy), at the distances
    ``steps`` (T,, increasing, m) short of its ``reach`` (m), lies in a cell whose glass log-odds (float32
    ``glass`` (h, w), corner (ox, oy), cell ``res`` m) gives p(glass) = 1 / (1 + exp(-lo)) > 0.5; samples off the
    grid or not finite are not glass. Each beam stops at its first glass sample or at its reach."""
    n, h, w = ux.shape[0], glass.shape[0], glass.shape[1]
    out = np.zeros(n, np.bool_)
    for i in range(n):
        for t in range(steps.shape[0]):
            s = steps[t]
            if not s < reach[i]:
                break
            x = lx + s * ux[i]
            y = ly + s * uy[i]
            if not (np.isfinite(x) and np.isfinite(y)):
                continue
            cx = np.int64(np.floor((x - ox) / res))
            cy = np.int64(np.floor((y - oy) / res))
            if cx < 0 or cx >= w or cy < 0 or cy >= h:
                continue
            lo = np.float64(glass[cy, cx])
            if lo > 0.0 and 1.0 / (1.0 + np.exp(-lo)) > 0.5:  # (lo <= 0 or NaN: p <= 0.5 or NaN, no exp needed)
                out[i] = True
                break
    return out
