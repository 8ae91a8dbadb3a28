"""Compiled pair expansion of the simulated laser's ray casting (:mod:`glassmap.sim.laser`), numba ``njit``.

Produces the same (beam, mirror, segment) triples in the same order as the numpy expansion it replaced, so
the simulated scans are the same to the last bit. Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

from glassmap.jit import njit
import numpy as np


@njit(cache=True, nogil=True, error_model="numpy")
def mirror_pairs(k0: np.ndarray, k1: np.ndarray, k0b: np.ndarray, k1b: np.ndarray, front: np.ndarray,
                 bmin: np.ndarray, bmax: np.ndarray, beam_mirror: np.ndarray,
                 mirrors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (beam, mirror, segment) triples to intersect: for mirror j (of ``mirrors``, segment ids) and
    segment k in front of it, the beams in [max(k0, bmin_j), min(k1, bmax_j)] and in the same interval one
    turn lower (k0b, k1b), that mirror j reflects (``beam_mirror[b] == j``), k not being the mirror itself.
    k0 .. k1b: (mirrors, segments) beam-index bounds (floats); front: (mirrors, segments) bool. Returns
    (beam, mirror index, segment) int64 arrays, mirror by mirror, then bounds (k0, k1) for every segment
    before (k0b, k1b), segment by segment, beams increasing."""
    nm, m = k0.shape
    total = 0
    for rep in range(2):
        if rep == 1:
            bb = np.empty(total, np.int64)
            jj = np.empty(total, np.int64)
            kk = np.empty(total, np.int64)
            total = 0
        for j in range(nm):
            lo_b, hi_b = float(bmin[j]), float(bmax[j])
            for half in range(2):
                for k in range(m):
                    if not front[j, k] or k == mirrors[j]:
                        continue
                    lo = np.int64(max(k0[j, k] if half == 0 else k0b[j, k], lo_b))
                    hi = np.int64(min(k1[j, k] if half == 0 else k1b[j, k], hi_b))
                    for b in range(lo, hi + 1):
                        if beam_mirror[b] == j:
                            if rep == 1:
                                bb[total], jj[total], kk[total] = b, j, k
                            total += 1
    return bb, jj, kk


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the kernel now, with the argument types the ray
    casting passes, rather than at the first scan that sees a mirror."""
    f = np.zeros((1, 1))
    i = np.zeros(1, np.int64)
    mirror_pairs(f, f, f, f, np.zeros((1, 1), np.bool_), i, i, i, i)
