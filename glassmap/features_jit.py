"""Compiled per-beam loops of the context model's features (:mod:`glassmap.glass_features`), numba ``njit``.

The same floating-point operations in the same order as the numpy code they replaced (no fast-math), so
the features are the same to the last bit; logarithms, sines and cosines and the sums whose numpy order
is pairwise stay in numpy. Beam index b runs over the n beams of one scan; segment ids are those of
:class:`glassmap.angles.IncidenceResult` (-1: none). Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

from .jit import njit
import numpy as np

_jit = njit(cache=True, nogil=True, error_model="numpy")  # x / 0 is inf or NaN, as in numpy


@_jit
def segment_order(seg: np.ndarray, n_seg: int) -> tuple[np.ndarray, np.ndarray]:
    """The beams on a segment grouped by segment id (increasing), in beam order within a group: (order
    (m,) beam indices, starts (g,) first position of each group in ``order``)."""
    count = np.zeros(n_seg, np.int64)
    for b in range(seg.shape[0]):
        if seg[b] >= 0:
            count[seg[b]] += 1
    pos = np.empty(n_seg, np.int64)
    g = 0
    total = 0
    for s in range(n_seg):
        pos[s] = total
        total += count[s]
        if count[s]:
            g += 1
    order = np.empty(total, np.int64)
    starts = np.empty(g, np.int64)
    k = 0
    for s in range(n_seg):
        if count[s]:
            starts[k] = pos[s]
            k += 1
    for b in range(seg.shape[0]):
        s = seg[b]
        if s >= 0:
            order[pos[s]] = b
            pos[s] += 1
    return order, starts


@_jit
def segment_groups(seg: np.ndarray, n_seg: int, r: np.ndarray, cos_a: np.ndarray, sin_a: np.ndarray,
                   li: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`segment_order` of the segment ids ``seg`` (n,), then ``li`` (n,) in that order (m,) and each
    group's extent (g,) m: the diagonal of the bounding box of its end points r * (cos_a, sin_a) (r: ranges
    (n,) m, cos_a, sin_a: the beam directions (n,)). Returns (order, starts, li in order, extents)."""
    order, starts = segment_order(seg, n_seg)
    g = starts.shape[0]
    m = order.shape[0]
    li_order = np.empty(m)
    ext = np.empty(g)
    for s in range(g):
        i0 = starts[s]
        i1 = starts[s + 1] if s + 1 < g else m
        b = order[i0]
        xmin = xmax = r[b] * cos_a[b]
        ymin = ymax = r[b] * sin_a[b]
        for i in range(i0, i1):
            b = order[i]
            px, py = r[b] * cos_a[b], r[b] * sin_a[b]
            xmin, xmax = min(xmin, px), max(xmax, px)
            ymin, ymax = min(ymin, py), max(ymax, py)
            li_order[i] = li[b]
        ext[s] = math.hypot(xmax - xmin, ymax - ymin)
    return order, starts, li_order, ext


@_jit
def _max_table(w: np.ndarray, levels: int) -> np.ndarray:
    """Sparse table of running maxima: row k, column i holds max(w[i : i + 2^k]) (clipped at the end)."""
    n = w.shape[0]
    table = np.empty((levels + 1, n))
    table[0] = w
    for k in range(1, levels + 1):
        span = 1 << (k - 1)
        for i in range(n):
            a = table[k - 1, i]
            if i + span < n:
                c = table[k - 1, i + span]
                a = a if a >= c else c
            table[k, i] = a
    return table


@_jit
def _window_max(table: np.ndarray, lo: int, hi: int) -> float:
    """max(w[lo : hi + 1]) from :func:`_max_table` (the window no longer than twice its last level's span)."""
    k = 0
    while k + 1 < table.shape[0] and (2 << k) <= hi - lo + 1:
        k += 1
    a = table[k, lo]
    c = table[k, hi - (1 << k) + 1]
    return a if a >= c else c


@_jit
def context_columns(x: np.ndarray, li: np.ndarray, r: np.ndarray, incidence: np.ndarray, e: np.ndarray,
                    lei: np.ndarray, order: np.ndarray, starts: np.ndarray, lsum: np.ndarray,
                    log_ext: np.ndarray) -> None:
    """Fill every column of the context features ``x`` (n, 19) float32.

    li: (n,) log1p of the intensities (0 where none); r: (n,) first-echo ranges (m); e, lei: (n, k) further
    echoes (m) and log1p of their intensities (k = 0: a single-echo scan; lei (n, 0): no intensities);
    order, starts: from :func:`segment_order`; lsum: (g,) sums of li over each group; log_ext: (g,) log1p
    of each group's extent (:func:`segment_groups`), column 15."""
    n = r.shape[0]
    ne = e.shape[1]
    two = np.zeros(n, np.bool_)
    for b in range(n):
        rb = r[b]
        ok = math.isfinite(rb)
        x[b, 0] = li[b]
        x[b, 1] = rb if ok else 0.0
        a = abs(incidence[b])
        x[b, 2] = a if a >= 0.0 else 0.0
        col = ne - 1
        for c in range(ne - 1, -1, -1):  # the last echo that differs from the first
            v = e[b, c]
            if abs(v - rb) > 1e-6 and math.isfinite(v):
                two[b] = True
                col = c
                break
        if two[b]:
            gap = e[b, col] - rb
            x[b, 4] = min(max(gap, -5.0), 10.0)
            x[b, 5] = lei[b, col] if lei.shape[1] > 0 and lei[b, col] > 0.0 else 0.0
        else:
            x[b, 4] = 0.0
            x[b, 5] = 0.0
        x[b, 3] = 2.0 if two[b] else 1.0
    # neighbours along the scan (beams without a reading count as the centre's value)
    w = np.empty(n)  # what a window's maximum is taken over: li where the beam has a reading
    for b in range(n):
        v = li[b]
        w[b] = v if math.isfinite(r[b]) and v == v else -np.inf
    table = _max_table(w, 4)  # windows of up to 2 * 2^4 beams
    n_two = np.zeros(n + 1, np.int64)  # two-echo beams before each beam
    for b in range(n):
        n_two[b + 1] = n_two[b] + two[b]
    for b in range(n):
        lb = li[b]
        for j, k in enumerate((-2, -1, 1, 2)):
            q = b + k
            d = li[q] - lb if 0 <= q < n and math.isfinite(r[q]) else np.nan
            x[b, 6 + j] = d if d == d else 0.0
        m3 = _window_max(table, max(b - 3, 0), min(b + 3, n - 1))
        m10 = _window_max(table, max(b - 10, 0), min(b + 10, n - 1))
        x[b, 10] = max(m3, lb) - lb
        x[b, 11] = max(m10, lb) - lb
        hi = r[b + 1] if b + 1 < n else r[n - 1]
        lo = r[b - 1] if b > 0 else r[0]
        hi = hi if math.isfinite(hi) else np.nan
        lo = lo if math.isfinite(lo) else np.nan
        slope = abs(hi - lo) * 0.5
        x[b, 12] = slope if slope <= 1.0 else 1.0
        lo3, hi3 = max(b - 3, 0), min(b + 4, n)
        x[b, 13] = float(n_two[hi3] - n_two[lo3]) / float(hi3 - lo3)
        x[b, 14] = 1.0
        x[b, 15] = 0.0
        x[b, 16] = 0.0
        x[b, 17] = 0.0
        x[b, 18] = 0.0
    # place on the line segment
    g = starts.shape[0]
    m = order.shape[0]
    for s in range(g):
        i0 = starts[s]
        i1 = starts[s + 1] if s + 1 < g else m
        cnt = float(i1 - i0)
        lo_i, hi_i = float(order[i0]), float(order[i1 - 1])
        mid = 0.5 * (lo_i + hi_i)
        half = max(0.5 * (hi_i - lo_i), 0.5)
        lmax = li[order[i0]]
        t = 0.0
        for i in range(i0, i1):
            lmax = max(lmax, li[order[i]])
            if two[order[i]]:
                t += 1.0
        mean = lsum[s] / cnt
        for i in range(i0, i1):
            b = order[i]
            x[b, 14] = abs(float(b) - mid) / half
            x[b, 15] = log_ext[s]
            x[b, 16] = mean - li[b]
            x[b, 17] = lmax - li[b]
            x[b, 18] = t / cnt
