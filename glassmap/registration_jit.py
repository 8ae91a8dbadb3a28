"""Compiled inner loops of the registration (:mod:`glassmap.registration`), numba ``njit``.

The same floating-point operations in the same order as the numpy code they replaced (no fast-math), so
the cells and sums are the same to the last bit; float32 stays float32 where numpy computed in float32.
Cells are (ix, iy) of a grid of ``h`` rows and ``w`` columns, flat index ``iy * w + ix``. Compiled code is
cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

from .jit import njit
import numpy as np

_jit = njit(cache=True, nogil=True, error_model="numpy")  # x / 0 is inf or NaN, as in numpy


@_jit
def nearest_cells(f: np.ndarray, occ: np.ndarray, w: int, h: int, thr: np.float32,
                  offs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c_hat per end point. f: (n, 2) end points in cell units from the grid origin; occ: flat float32
    log-odds; thr: occupied above this (float32). The end-point cell when it is occupied or its search
    window (``offs``, (q, 2) offsets without the centre, in window order) is not wholly inside the grid or
    holds no occupied cell; else the occupied window cell whose centre is nearest to the end point (the
    first in window order on a tie, float32 distances). Returns (cells (n, 2) int64, found (n,) bool)."""
    n = f.shape[0]
    radius = 0
    for q in range(offs.shape[0]):
        radius = max(radius, abs(offs[q, 0]), abs(offs[q, 1]))
    cells = np.empty((n, 2), np.int64)
    found = np.zeros(n, np.bool_)
    half = np.float32(0.5)
    for j in range(n):
        bx, by = np.int64(math.floor(f[j, 0])), np.int64(math.floor(f[j, 1]))
        cells[j, 0], cells[j, 1] = bx, by
        if bx < 0 or bx >= w or by < 0 or by >= h:
            continue
        if occ[by * w + bx] > thr:
            found[j] = True
            continue
        if offs.shape[0] == 0 or bx < radius or bx >= w - radius or by < radius or by >= h - radius:
            continue
        fx, fy = np.float32(f[j, 0] - bx), np.float32(f[j, 1] - by)
        best = np.float32(np.inf)
        k = -1
        for q in range(offs.shape[0]):
            if occ[(by + offs[q, 1]) * w + bx + offs[q, 0]] > thr:
                dx = (np.float32(offs[q, 0]) + half) - fx
                dy = (np.float32(offs[q, 1]) + half) - fy
                d2 = dx * dx + dy * dy
                if k < 0 or d2 < best:
                    best, k = d2, q
        if k >= 0:
            cells[j, 0], cells[j, 1] = bx + offs[k, 0], by + offs[k, 1]
            found[j] = True
    return cells, found


@_jit
def window_observations(cells: np.ndarray, lo: np.ndarray, spread: np.ndarray, offs: np.ndarray, w: int,
                        h: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat cells and log-odds of the window cells around each c_hat (beam by beam, window cells in
    ``offs`` order): window cell q of beam j gets ``lo[j, spread[q]]``; cells outside the grid and
    log-odds of exactly 0 are left out."""
    n, q = cells.shape[0], offs.shape[0]
    flat = np.empty(n * q, np.int64)
    val = np.empty(n * q)
    m = 0
    for j in range(n):
        cx, cy = cells[j, 0], cells[j, 1]
        for i in range(q):
            x, y = cx + offs[i, 0], cy + offs[i, 1]
            v = lo[j, spread[i]]
            if x >= 0 and x < w and y >= 0 and y < h and v != 0.0:
                flat[m] = y * w + x
                val[m] = v
                m += 1
    return flat[:m], val[:m]


@_jit
def sum_runs(cells: np.ndarray, order: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per distinct cell of ``cells`` (sorted; ``order``: the observation each entry came from, increasing
    within a cell): the cell, the sum of its observations' ``values`` added in observation order, and
    their number."""
    m = cells.shape[0]
    uniq = np.empty(m, np.int64)
    total = np.empty(m)
    count = np.empty(m, np.int64)
    u = -1
    for i in range(m):
        if i == 0 or cells[i] != cells[i - 1]:
            u += 1
            uniq[u] = cells[i]
            total[u] = 0.0
            count[u] = 0
        total[u] += values[order[i]]
        count[u] += 1
    return uniq[:u + 1], total[:u + 1], count[:u + 1]


@_jit
def decay_exponents(dist: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The exponents -dist^2 / (2 sigma^2) (n, d) of eq. 6 for each beam (sigma (n,) m) and window
    distance (dist (d,) m); sigma = 0 gives -inf or NaN (see :func:`decayed`)."""
    n, d = sigma.shape[0], dist.shape[0]
    ex = np.empty((n, d))
    for j in range(n):
        s2 = 2.0 * sigma[j] * sigma[j]
        for i in range(d):
            ex[j, i] = -(dist[i] * dist[i]) / s2
    return ex


@_jit
def decayed(p: np.ndarray, w: np.ndarray, dist: np.ndarray, sigma: np.ndarray, p_clip: float,
            p_max: float) -> np.ndarray:
    """Eq. 6 from the weights ``w = exp(exponent)`` (n, d): (p - 0.5) w + 0.5 clipped to [p_clip, p_max];
    sigma = 0 weighs 1 at distance 0 and 0 elsewhere."""
    n, d = w.shape
    out = np.empty((n, d))
    for j in range(n):
        for i in range(d):
            wi = w[j, i] if sigma[j] > 0 else (1.0 if dist[i] == 0 else 0.0)
            out[j, i] = min(max((p[j] - 0.5) * wi + 0.5, p_clip), p_max)
    return out


@_jit
def update_windows(layer: np.ndarray, cells: np.ndarray, lo: np.ndarray, spread: np.ndarray, offs: np.ndarray,
                   w: int, h: int, drop_zero: bool, mean: bool, l_min: float, l_max: float, returns: np.ndarray,
                   centre: int) -> int:
    """:func:`window_observations`, then per cell their sum (``mean``: divided by their number) added to the
    flat float32 log-odds ``layer`` clamped to [l_min, l_max], in one pass without sorting: observations of
    exactly 0 are left out only if ``drop_zero``. A cell's observations are added in observation order (beam
    by beam, window cells in ``offs`` order) from 0.0, as :func:`sum_runs` does; the update is that of
    ``layer[c] = clip(layer[c] + delta, l_min, l_max)`` in float64 stored as float32. Returns the number of
    cells updated.

    ``centre`` >= 0 (the index of offset (0, 0) in ``offs``): the other window cells' evidence is scaled
    towards 0.5 by their visibility, (1 - q) + q * returns[j] with q the cell's p(glass) before this scan and
    ``returns[j]`` (n,) the chance that glass returns beam j (see ``glassmap.mapping.MapperConfig.visibility``).
    """
    n, q = cells.shape[0], offs.shape[0]
    bits = 1
    while (1 << bits) < 2 * n * q:
        bits += 1
    mask = (1 << bits) - 1
    shift = np.uint64(64 - bits)
    fib = np.uint64(0x9E3779B97F4A7C15)  # multiplicative (Fibonacci) hashing of the flat cell index
    slot = np.full(1 << bits, -1, np.int32)  # open addressing, linear probing: the cell's entry or -1
    key = np.empty(n * q, np.int64)
    total = np.empty(n * q)
    count = np.empty(n * q, np.int64)
    vis = centre >= 0
    q_glass = np.empty(n * q if vis else 0)  # per entry: the cell's p(glass) before this scan
    half = np.empty(lo.shape[1])  # per beam: eq. 6's decayed p - 0.5 at each window distance
    u = 0
    for j in range(n):
        cx, cy = cells[j, 0], cells[j, 1]
        if vis:
            for k in range(lo.shape[1]):
                half[k] = 1.0 / (1.0 + math.exp(-lo[j, k])) - 0.5
        for i in range(q):
            x, y = cx + offs[i, 0], cy + offs[i, 1]
            v = lo[j, spread[i]]
            if x < 0 or x >= w or y < 0 or y >= h or (drop_zero and v == 0.0):
                continue
            c = y * w + x
            b = np.int64((np.uint64(c) * fib) >> shift)
            while True:
                s = slot[b]
                if s < 0:
                    s = u
                    slot[b] = np.int32(s)
                    key[s] = c
                    total[s] = 0.0
                    count[s] = 0
                    if vis:
                        q_glass[s] = 1.0 / (1.0 + math.exp(-np.float64(layer[c])))
                    u += 1
                    break
                if key[s] == c:
                    break
                b = (b + 1) & mask
            if vis and i != centre:
                p = half[spread[i]] * (1.0 - q_glass[s] + q_glass[s] * returns[j]) + 0.5
                v = math.log(p / (1.0 - p))
            total[s] += v
            count[s] += 1
    for s in range(u):
        d = total[s] / np.float64(count[s]) if mean else total[s]
        c = key[s]
        layer[c] = np.float32(min(max(np.float64(layer[c]) + d, l_min), l_max))
    return u
