"""Compiled per-beam loops of :func:`runtime.messages.last_echo` and :func:`runtime.messages.as_recorded_scan`,
numba ``njit`` (loaded at first use, see :mod:`glassmap.jit`). The same values as the numpy code they
replaced, bit for bit. Compiled code is cached on disk (``cache=True``)."""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit

_BIG = np.finfo(np.float64).max  # np.nan_to_num's replacement for +inf


@njit(cache=True, nogil=True)
def last_echoes(r: np.ndarray, e: np.ndarray, ei: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per beam of ranges ``r`` (n,) (m), the last column of echoes ``e`` (n, k) (m) that is finite and
    differs from the beam's range by more than 1e-6 m, and its intensity in ``ei`` (n, k) (NaN read as 0,
    +-inf as the largest finite float); NaN and 0 where there is none."""
    n, k = e.shape
    lr = np.empty(n, np.float64)
    li = np.empty(n, np.float64)
    for i in range(n):
        lr[i], li[i] = np.nan, 0.0
        if not np.isfinite(r[i]):
            continue
        for j in range(k - 1, -1, -1):
            v = e[i, j]
            if np.isfinite(v) and abs(v - r[i]) > 1e-6:
                lr[i] = v
                x = ei[i, j]
                li[i] = 0.0 if np.isnan(x) else (_BIG if x == np.inf else (-_BIG if x == -np.inf else x))
                break
    return lr, li


@njit(cache=True, nogil=True)
def recorded_last_echoes(r: np.ndarray, e: np.ndarray,
                         ei: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ranges ``r`` (n,) (m) and :func:`last_echoes` as a LaserScan records them: each value rounded
    to float32 and back; (ranges (n,), last echoes (n, 1), their intensities (n, 1))."""
    lr, li = last_echoes(r, e, ei)
    n = r.shape[0]
    rr = np.empty(n, np.float64)
    er = np.empty((n, 1), np.float64)
    ir = np.empty((n, 1), np.float64)
    for i in range(n):
        rr[i] = np.float64(np.float32(r[i]))
        er[i, 0] = np.float64(np.float32(lr[i]))
        ir[i, 0] = np.float64(np.float32(li[i]))
    return rr, er, ir


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the kernels now, with the argument types
    :mod:`runtime.messages` passes, rather than at the first multi-echo scan."""
    last_echoes(np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1)))
    recorded_last_echoes(np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1)))
