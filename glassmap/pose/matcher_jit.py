"""Compiled lookups of the correlative scan matcher (:mod:`glassmap.pose.matcher`), numba ``njit``.

Each kernel does the floating-point operations of the numpy code it replaced in the same order (no
fast-math; float32 stays float32), so its output is the same to the last bit; the transcendental functions
and the weighted sums over the end points (a BLAS product) stay in numpy. Poses: yaws (K,) as their cosines
and sines, translations as flat cell offsets ``off`` (T,) of the field (``ty * width + tx``); end points
(n,) in the base frame (m); ``ox``, ``oy`` (1,) or (K,): the map-frame origin of the poses minus the
field's corner (m), one for all yaws or one per yaw. Results are (K, T, n) float32 per end point.
Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def cell_values(field: np.ndarray, px: np.ndarray, py: np.ndarray, c: np.ndarray, s: np.ndarray, ox: np.ndarray,
                oy: np.ndarray, res: float, off: np.ndarray, margin: int, w: int, h: int) -> np.ndarray:
    """The flat field's value in the cell each end point falls in, for every pose; points off the crop are
    clamped into its border (``margin`` cells wide, at least the largest translation)."""
    k_n, t_n, n = c.shape[0], off.shape[0], px.shape[0]
    out = np.empty((k_n, t_n, n), np.float32)
    base = np.empty(n, np.int64)
    for k in range(k_n):
        kx, ky = (k if ox.shape[0] > 1 else 0), (k if oy.shape[0] > 1 else 0)
        for j in range(n):
            fx = (c[k] * px[j] - s[k] * py[j] + ox[kx]) / res
            fy = (s[k] * px[j] + c[k] * py[j] + oy[ky]) / res
            ix = min(max(np.int64(np.floor(fx)), margin), w - 1 - margin)
            iy = min(max(np.int64(np.floor(fy)), margin), h - 1 - margin)
            base[j] = iy * w + ix
        for t in range(t_n):
            o = off[t]
            for j in range(n):
                out[k, t, j] = field[base[j] + o]
    return out


@_jit
def scaled_squared_distances(vx: np.ndarray, vy: np.ndarray, px: np.ndarray, py: np.ndarray, c: np.ndarray,
                             s: np.ndarray, ox: np.ndarray, oy: np.ndarray, res: float, off: np.ndarray, margin: int,
                             w: int, h: int, scale: np.float32) -> np.ndarray:
    """``scale`` times the squared length of the vector to the nearest wall point, that vector interpolated
    bilinearly between the four cell centres around each end point (float32, corners in the order (0, 0),
    (1, 0), (0, 1), (1, 1)); points off the crop are clamped into its border."""
    k_n, t_n, n = c.shape[0], off.shape[0], px.shape[0]
    out = np.empty((k_n, t_n, n), np.float32)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for k in range(k_n):
        kx, ky = (k if ox.shape[0] > 1 else 0), (k if oy.shape[0] > 1 else 0)
        for j in range(n):  # one point at a time: its translations read neighbouring cells
            gx = (c[k] * px[j] - s[k] * py[j] + ox[kx]) / res - 0.5
            gy = (s[k] * px[j] + c[k] * py[j] + oy[ky]) / res - 0.5
            x0, y0 = np.floor(gx), np.floor(gy)
            ax, ay = np.float32(gx - x0), np.float32(gy - y0)
            ix = min(max(np.int64(x0), margin), w - 2 - margin)
            iy = min(max(np.int64(y0), margin), h - 2 - margin)
            a00, a10, a01, a11 = (one - ax) * (one - ay), ax * (one - ay), (one - ax) * ay, ax * ay
            for t in range(t_n):
                b = iy * w + ix + off[t]
                sx = zero + vx[b] * a00
                sy = zero + vy[b] * a00
                sx = sx + vx[b + 1] * a10
                sy = sy + vy[b + 1] * a10
                sx = sx + vx[b + w] * a01
                sy = sy + vy[b + w] * a01
                sx = sx + vx[b + w + 1] * a11
                sy = sy + vy[b + w + 1] * a11
                out[k, t, j] = (sx * sx + sy * sy) * scale
    return out
