"""Compiled elementwise passes of the classifier network (:meth:`glassmap.classifier.GlassClassifier.logits`),
numba ``njit``.

The same float32 operations in the same order as the numpy code they replaced (no fast-math), so the
activations are the same to the last bit (a ReLU of -0.0 may keep its sign, which no later product or sum
can tell from +0.0); the matrix products stay in numpy (BLAS). Rows are beams, columns features or units.
Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from .jit import njit

_jit = njit(cache=True, nogil=True)


@_jit
def standardise(x: np.ndarray, mean: np.ndarray, inv_std: np.ndarray) -> np.ndarray:
    """(x - mean) * inv_std per column, float32 (m, k) from float32 x (m, k), mean (k,), inv_std (k,)."""
    m, k = x.shape
    out = np.empty((m, k), np.float32)
    for i in range(m):
        for j in range(k):
            out[i, j] = (x[i, j] - mean[j]) * inv_std[j]
    return out


@_jit
def standardise_rows(x: np.ndarray, use: np.ndarray, mean: np.ndarray,
                     inv_std: np.ndarray) -> tuple[np.ndarray, bool]:
    """:func:`standardise` of the rows ``use`` (n,) bool of float32 x (n, k), and whether all their raw values
    are finite."""
    m = 0
    for i in range(x.shape[0]):
        m += use[i]
    k = x.shape[1]
    out = np.empty((m, k), np.float32)
    finite = True
    r = 0
    for i in range(x.shape[0]):
        if use[i]:
            for j in range(k):
                v = x[i, j]
                finite = finite and np.isfinite(v)
                out[r, j] = (v - mean[j]) * inv_std[j]
            r += 1
    return out, finite


@_jit
def negative_logit_gaps(lg: np.ndarray) -> np.ndarray:
    """-(l1 - l0) (m,) float64 of the float32 logits (m, 2) over {not glass, glass}."""
    m = lg.shape[0]
    out = np.empty(m)
    for i in range(m):
        out[i] = -(np.float64(lg[i, 1]) - np.float64(lg[i, 0]))
    return out


@_jit
def add_bias_relu(h: np.ndarray, b: np.ndarray) -> None:
    """In place: h = max(h + b, 0) per row, float32 h (m, u), b (u,) (NaN stays NaN, as np.maximum)."""
    m, u = h.shape
    for i in range(m):
        for j in range(u):
            v = h[i, j] + b[j]
            h[i, j] = v if not v < 0.0 else np.float32(0.0)
