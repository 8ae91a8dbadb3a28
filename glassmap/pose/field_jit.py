"""Compiled passes of the likelihood field (:mod:`glassmap.pose.field`), numba ``njit``.

A maximum is exact, so the result equals scipy's to the last bit whatever the order of the comparisons (the
field holds no NaN). Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def forward_maximum(a: np.ndarray, f: int) -> np.ndarray:
    """out[y, x] = max of a[y .. y + f - 1, x .. x + f - 1], indices past the last row / column clamped to
    it: ``scipy.ndimage.maximum_filter(a, size=f, origin=-(f // 2), mode="nearest")`` for a 2-D array
    without NaN."""
    h, w = a.shape
    rows = np.empty((h, w), a.dtype)
    for y in range(h):
        for x in range(w):
            m = a[y, x]
            for d in range(1, f):
                v = a[y, min(x + d, w - 1)]
                if v > m:
                    m = v
            rows[y, x] = m
    out = np.empty((h, w), a.dtype)
    for y in range(h):
        out[y, :] = rows[y, :]
        for d in range(1, f):
            r = rows[min(y + d, h - 1)]
            for x in range(w):
                if r[x] > out[y, x]:
                    out[y, x] = r[x]
    return out


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the kernel now, with the argument types the field
    passes, rather than at the first rebuild."""
    forward_maximum(np.zeros((1, 1), np.float32), 1)
