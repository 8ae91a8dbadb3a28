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
def add_bias_relu(h: np.ndarray, b: np.ndarray) -> None:
    """In place: h = max(h + b, 0) per row, float32 h (m, u), b (u,) (NaN stays NaN, as np.maximum)."""
    m, u = h.shape
    for i in range(m):
        for j in range(u):
            v = h[i, j] + b[j]
            h[i, j] = v if not v < 0.0 else np.float32(0.0)
