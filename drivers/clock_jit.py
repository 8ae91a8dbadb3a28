"""Compiled lower-envelope fit of :mod:`drivers.clock`, numba ``njit`` (loaded at first use, see
:mod:`glassmap.jit`). The same line as the numpy code it replaced, bit for bit (its summation order and
``np.interp``'s arithmetic included). Compiled code is cached on disk (``cache=True``)."""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit


@njit(cache=True, nogil=True)
def _sum(x: np.ndarray) -> float:
    """``x.sum()`` as numpy adds float64 up (pairwise, eight running sums per block of up to 128)."""
    n = x.shape[0]
    if n < 8:
        res = 0.0
        for i in range(n):
            res += x[i]
        return res
    if n <= 128:
        r = x[:8].copy()
        i = 8
        while i < n - n % 8:
            for k in range(8):
                r[k] += x[i + k]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += x[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _sum(x[:n2]) + _sum(x[n2:])


@njit(cache=True, nogil=True)
def near_lower_hull(s: np.ndarray, a: np.ndarray, tol: float) -> np.ndarray:
    """Indices (ascending) of the points (s_i, a_i) at most ``tol`` above the lower convex hull of all of
    them (monotone chain over the points sorted by s, then a); a point with the least a of several equal s
    stands for them on the hull, the others are measured against it."""
    n = s.shape[0]
    order = np.arange(n)
    for p in range(1, n):  # stable insertion sort by (s, a): np.lexsort((a, s))
        q, k = order[p], p
        while k > 0 and (s[order[k - 1]] > s[q] or (s[order[k - 1]] == s[q] and a[order[k - 1]] > a[q])):
            order[k] = order[k - 1]
            k -= 1
        order[k] = q
    hx = np.empty(n)
    hy = np.empty(n)
    m = 0
    for p in range(n):
        x, y = s[order[p]], a[order[p]]
        if p > 0 and x == s[order[p - 1]]:
            continue
        while m >= 2 and (hx[m - 1] - hx[m - 2]) * (y - hy[m - 2]) - (hy[m - 1] - hy[m - 2]) * (x - hx[m - 2]) <= 0:
            m -= 1
        hx[m], hy[m] = x, y
        m += 1
    near = np.empty(n, np.int64)
    cnt = 0
    for p in range(n):
        x = s[p]
        j = 0  # np.interp(x, hx[:m], hy[:m]): the last hull point at or left of x
        while j + 1 < m and hx[j + 1] <= x:
            j += 1
        if x <= hx[0]:
            h = hy[0]
        elif j == m - 1 or hx[j] == x:
            h = hy[j]
        else:
            h = (hy[j + 1] - hy[j]) / (hx[j + 1] - hx[j]) * (x - hx[j]) + hy[j]
        if a[p] - h <= tol:
            near[cnt] = p
            cnt += 1
    return near[:cnt]


@njit(cache=True, nogil=True)
def lower_envelope(s: np.ndarray, a: np.ndarray) -> tuple[int, float, float]:
    """The line a = c + b s of :func:`drivers.clock._lower_envelope` over sensor times ``s`` (s) and
    arrivals ``a`` (host s), both relative to the first point: (status, c, b), status 1 for a line, 0 for
    none below them all with a positive slope, -1 for no two points near the hull at different s."""
    near = near_lower_hull(s, a, 1e-6)
    n = s.shape[0]
    resid = np.empty(n)
    best, bc, bb, pairs = np.inf, 0.0, 0.0, 0
    for u in range(near.shape[0]):  # pairs in np.triu_indices' order; the first least cost wins
        i = near[u]
        for v in range(u + 1, near.shape[0]):
            j = near[v]
            ds = s[j] - s[i]
            if not ds > 0:
                continue
            pairs += 1
            b = (a[j] - a[i]) / ds
            c = a[i] - b * s[i]
            low = np.inf
            for p in range(n):
                resid[p] = a[p] - (c + b * s[p])
                low = min(low, resid[p])
            if low >= -1e-9 and b > 0:
                cost = 0.0 + _sum(resid)
                if cost < best:
                    best, bc, bb = cost, c, b
    if pairs == 0:
        return -1, 0.0, 0.0
    if best == np.inf:
        return 0, 0.0, 0.0
    return 1, bc, bb


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the kernels now, with the argument types
    :class:`drivers.clock.ClockMapper` passes, rather than at its first fit (in a client's event loop)."""
    lower_envelope(np.arange(4.0), np.arange(4.0))
