"""Compiled inner loops of split-and-merge line extraction (:mod:`glassmap.angles`), numba ``njit``.

Each kernel does, point by point in scan order, what the numpy version of :mod:`glassmap.angles` did in
whole-array passes, with the same floating-point operations in the same order (no fast-math, so no fused
multiply-adds), so its results are the same to the last bit. Transcendental functions (sin, cos, arctan2,
arccos) stay in numpy: numpy's SIMD versions may round differently from the C library numba calls. hypot
is the C library's in both. Points are in the laser frame (metres); ``is_start`` marks the first point of
each piece. Compiled code is cached on disk (``cache=True``): only the first run on a machine compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def split_pieces(x: np.ndarray, y: np.ndarray, tol: np.ndarray, is_start: np.ndarray, min_len: int,
                 max_levels: int) -> np.ndarray:
    """Iterative end-point fit: returns a copy of ``is_start`` with every split added.

    A piece (first to last point) is split at its first farthest point from the chord when that point's
    distance exceeds its tolerance ``tol`` (m) and the piece spans at least ``min_len`` points after its
    first; the two halves are fitted again, down to ``max_levels`` levels below the runs of ``is_start``.
    A chord shorter than 1e-9 m (a closed piece) measures distances to the first point."""
    n = x.shape[0]
    out = is_start.copy()
    if n == 0:
        return out
    # a stack of pieces (first, last, level): at most one piece per point is waiting at any time
    first = np.empty(n + 1, np.int64)
    last = np.empty(n + 1, np.int64)
    level = np.empty(n + 1, np.int64)
    top = 0
    end = n - 1
    for i in range(n - 1, -1, -1):
        if is_start[i]:
            first[top], last[top], level[top] = i, end, 0
            top += 1
            end = i - 1
    while top > 0:
        top -= 1
        s, e, d = first[top], last[top], level[top]
        if d >= max_levels or e - s < min_len:
            continue
        fx, fy = x[s], y[s]
        dx, dy = x[e] - fx, y[e] - fy
        length = math.hypot(dx, dy)
        best = -np.inf
        k = -1
        if length <= 1e-9:
            for i in range(s, e + 1):
                ex = math.hypot(x[i] - fx, y[i] - fy) - tol[i]
                if ex > best:
                    best, k = ex, i
        else:
            a, b = -dy / length, dx / length
            c = -(a * fx + b * fy)
            for i in range(s, e + 1):
                ex = abs(a * x[i] + b * y[i] + c) - tol[i]
                if ex > best:
                    best, k = ex, i
        if best > 0.0:
            out[k] = True
            first[top], last[top], level[top] = s, k - 1, d + 1
            top += 1
            first[top], last[top], level[top] = k, e, d + 1
            top += 1
    return out


@_jit
def moments(x: np.ndarray, y: np.ndarray, seg: np.ndarray, n_seg: int) -> np.ndarray:
    """Per-segment sums (n_seg, 6): count, sx, sy, sxx, syy, sxy, added in point order."""
    m = np.zeros((n_seg, 6))
    for i in range(x.shape[0]):
        s = seg[i]
        xi, yi = x[i], y[i]
        m[s, 0] += 1.0
        m[s, 1] += xi
        m[s, 2] += yi
        m[s, 3] += xi * xi
        m[s, 4] += yi * yi
        m[s, 5] += xi * yi
    return m


@_jit
def extents(x: np.ndarray, y: np.ndarray, seg: np.ndarray, cen: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Length (m) of each segment along its line (direction (n_y, -n_x)): largest minus smallest
    coordinate of its points; -inf for a segment without points."""
    k = cen.shape[0]
    lo = np.full(k, np.inf)
    hi = np.full(k, -np.inf)
    for i in range(x.shape[0]):
        s = seg[i]
        t = (x[i] - cen[s, 0]) * normals[s, 1] - (y[i] - cen[s, 1]) * normals[s, 0]
        lo[s] = min(lo[s], t)
        hi[s] = max(hi[s], t)
    return hi - lo


@_jit
def link_chains(x: np.ndarray, y: np.ndarray, r: np.ndarray, beam: np.ndarray, k: float, sigma3: float,
                max_lag: int, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The second pass's chains over m leftover points (scan order): each point links to the nearest
    earlier point up to ``max_lag`` points back that lies within ``min(r_i, r_j) * (beam_i - beam_j) * k +
    sigma3`` (m); a chain is a tree of links. Returns the points of chains of at least ``min_points`` points,
    chain by chain (chains by their first point, points in scan order), and a bool start mask of the chains
    over them."""
    m = x.shape[0]
    root = np.arange(m)
    for i in range(1, m):
        for lag in range(1, min(max_lag, i) + 1):
            j = i - lag
            thr = min(r[i], r[j]) * float(beam[i] - beam[j])
            thr *= k
            thr += sigma3
            if math.hypot(x[i] - x[j], y[i] - y[j]) <= thr:
                root[i] = root[j]
                break
    size = np.zeros(m, np.int64)
    for i in range(m):
        size[root[i]] += 1
    offset = np.zeros(m, np.int64)
    total = 0
    for i in range(m):  # roots in increasing order
        if size[i] >= min_points:
            offset[i] = total
            total += size[i]
    order = np.empty(total, np.int64)
    brk = np.zeros(total, np.bool_)
    fill = offset.copy()
    for i in range(m):
        q = root[i]
        if size[q] >= min_points:
            if fill[q] == offset[q]:
                brk[fill[q]] = True
            order[fill[q]] = i
            fill[q] += 1
    return order, brk


@_jit
def _nonneg(v: float) -> float:
    """np.maximum(v, 0.0): v unless v < 0."""
    return v if v >= 0.0 or v != v else 0.0


@_jit
def tls_moments(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least squares from moments (k, 6) up to the line direction: centroids (k, 2) m, the arguments
    (2, k) of the direction's arctan2 (2 c_xy, c_xx - c_yy; m^2) and the rms distance (k,) m of the points
    from their line (square root of the covariance's smaller eigenvalue)."""
    k = m.shape[0]
    cen = np.empty((k, 2))
    args = np.empty((2, k))
    rms = np.empty(k)
    for s in range(k):
        n = max(m[s, 0], 1.0)
        mx, my = m[s, 1] / n, m[s, 2] / n
        cxx = m[s, 3] / n - mx * mx
        cyy = m[s, 4] / n - my * my
        cxy = m[s, 5] / n - mx * my
        cen[s, 0], cen[s, 1] = mx, my
        args[0, s] = 2.0 * cxy
        args[1, s] = cxx - cyy
        tr = cxx + cyy
        det = cxx * cyy
        det -= cxy * cxy
        disc = 0.25 * tr
        disc *= tr
        disc -= det
        lam_min = 0.5 * tr
        lam_min -= math.sqrt(_nonneg(disc))
        rms[s] = math.sqrt(_nonneg(lam_min))
    return cen, args, rms
