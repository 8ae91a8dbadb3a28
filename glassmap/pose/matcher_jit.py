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
def _lattice_side(off: np.ndarray, w: int) -> int:
    """m when the flat offsets ``off`` (T,) are the square lattice of m x m cells ``off[0] + r * w + q``
    (r, q in 0 .. m - 1, q fastest), else 0."""
    m = int(np.sqrt(off.shape[0]) + 0.5)
    if m * m != off.shape[0]:
        return 0
    for r in range(m):
        for q in range(m):
            if off[r * m + q] != off[0] + r * w + q:
                return 0
    return m


@_jit
def _corner_weights(c: float, s: float, px: float, py: float, ox: float, oy: float, res: float, margin: int, w: int,
                    h: int) -> tuple[int, np.float32, np.float32, np.float32, np.float32]:
    """(flat index of the lower-left of the four cell centres around the end point (px, py) at yaw (c, s) and
    origin (ox, oy), clamped into the border; their bilinear weights (float32) in the corner order (0, 0),
    (1, 0), (0, 1), (1, 1))."""
    one = np.float32(1.0)
    gx = (c * px - s * py + ox) / res - 0.5
    gy = (s * px + c * py + oy) / res - 0.5
    x0, y0 = np.floor(gx), np.floor(gy)
    ax, ay = np.float32(gx - x0), np.float32(gy - y0)
    ix = min(max(np.int64(x0), margin), w - 2 - margin)
    iy = min(max(np.int64(y0), margin), h - 2 - margin)
    return iy * w + ix, (one - ax) * (one - ay), ax * (one - ay), (one - ax) * ay, ax * ay


@_jit
def scaled_squared_distances(vx: np.ndarray, vy: np.ndarray, px: np.ndarray, py: np.ndarray, c: np.ndarray,
                             s: np.ndarray, ox: np.ndarray, oy: np.ndarray, res: float, off: np.ndarray, margin: int,
                             w: int, h: int, scale: np.float32) -> np.ndarray:
    """``scale`` times the squared length of the vector to the nearest wall point, that vector interpolated
    bilinearly between the four cell centres around each end point (float32, corners in the order (0, 0),
    (1, 0), (0, 1), (1, 1)); points off the crop are clamped into its border. The translations ``off`` must be
    a square lattice of cells (``off[0] + r * w + q``, q fastest) inside the (h, w) arrays, else ValueError:
    for one translation the points of a yaw are evaluated in one loop, for more each point's row of
    translations reads neighbouring cells (both compile to vector code)."""
    k_n, t_n, n = c.shape[0], off.shape[0], px.shape[0]
    m = _lattice_side(off, w)
    if m == 0:
        raise ValueError("the translations are not a square lattice of cells")
    lo = min(margin, h - 2 - margin) * w + min(margin, w - 2 - margin) + off[0]  # the smallest and largest cell read
    hi = (h - 2 - margin) * w + (w - 2 - margin) + off[0] + (m - 1) * w + (m - 1) + w + 1
    if lo < 0 or hi >= vx.shape[0] or hi >= vy.shape[0]:
        raise ValueError("the translations reach past the field")
    out = np.empty((k_n, t_n, n), np.float32)
    zero = np.float32(0.0)
    uw, u1 = np.uint64(w), np.uint64(1)  # unsigned cell indices (all >= 0, checked): no wrap-around test
    base = np.empty(n, np.uint64)  # one translation: each point's cell and corner weights
    a00, a10, a01, a11 = (np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32),
                          np.empty(n, np.float32))
    row = np.empty(t_n, np.float32)  # more: one point's values, translation by translation
    for k in range(k_n):
        kx, ky = (k if ox.shape[0] > 1 else 0), (k if oy.shape[0] > 1 else 0)
        if m == 1:
            for j in range(n):
                b, a00[j], a10[j], a01[j], a11[j] = _corner_weights(c[k], s[k], px[j], py[j], ox[kx], oy[ky], res,
                                                                    margin, w, h)
                base[j] = np.uint64(b + off[0])
            for j in range(n):
                b = base[j]
                sx = zero + vx[b] * a00[j]
                sy = zero + vy[b] * a00[j]
                sx = sx + vx[b + u1] * a10[j]
                sy = sy + vy[b + u1] * a10[j]
                sx = sx + vx[b + uw] * a01[j]
                sy = sy + vy[b + uw] * a01[j]
                sx = sx + vx[b + uw + u1] * a11[j]
                sy = sy + vy[b + uw + u1] * a11[j]
                out[k, 0, j] = (sx * sx + sy * sy) * scale
            continue
        for j in range(n):
            b, w00, w10, w01, w11 = _corner_weights(c[k], s[k], px[j], py[j], ox[kx], oy[ky], res, margin, w, h)
            b0 = np.uint64(b + off[0])
            for r in range(m):
                br = b0 + np.uint64(r) * uw
                for q in range(m):
                    b = br + np.uint64(q)
                    sx = zero + vx[b] * w00
                    sy = zero + vy[b] * w00
                    sx = sx + vx[b + u1] * w10
                    sy = sy + vy[b + u1] * w10
                    sx = sx + vx[b + uw] * w01
                    sy = sy + vy[b + uw] * w01
                    sx = sx + vx[b + uw + u1] * w11
                    sy = sy + vy[b + uw + u1] * w11
                    row[r * m + q] = (sx * sx + sy * sy) * scale
            for t in range(t_n):
                out[k, t, j] = row[t]
    return out
