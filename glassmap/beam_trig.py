"""What the per-scan path needs of the beam angles alone (laser frame): their cosines, sines and median step,
computed once for the last angle array seen (a laser's beam angles are the same in every scan).

The values are numpy's ``np.cos`` / ``np.sin`` of the whole array; an element-wise function gives each
element the same number whatever else is in the array, so ``cos[idx]`` is ``np.cos(angles[idx])``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class BeamTrig:
    """Read-only per-beam arrays of one angle array: ``angles`` (n,) rad (a copy), ``cos`` and ``sin`` (n,),
    and ``median_step`` (rad): the median difference between consecutive angles (0 for fewer than 2)."""

    angles: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    median_step: float
    source: np.ndarray | None = None  # the array given, when read-only and owning its data (cannot change)


_last: BeamTrig | None = None  # replaced whole (one assignment), so threads sharing it see one or the other


def beam_trig(angles: np.ndarray) -> BeamTrig:
    """The :class:`BeamTrig` of ``angles`` (n,) rad: the last one if the values are the same (NaN never is);
    for the array it was made from, when that is read-only and owns its data (e.g. ``Scan.angles``), the
    values are not compared."""
    global _last
    a = np.asarray(angles, dtype=np.float64)
    last = _last
    if last is not None and a is last.source:
        return last
    fixed = a if not a.flags.writeable and a.flags.owndata else None
    if last is not None and last.angles.shape == a.shape and np.array_equal(last.angles, a):
        if fixed is not None:
            _last = last = replace(last, source=fixed)
        return last
    a = a.copy()
    c, s = np.cos(a), np.sin(a)
    for v in (a, c, s):
        v.flags.writeable = False
    _last = BeamTrig(a, c, s, median_step(a), fixed)
    return _last


def median_step(a: np.ndarray) -> float:
    """np.median(np.diff(a)) (0 for fewer than 2 angles), by a partial sort."""
    if a.size < 2:
        return 0.0
    d = np.diff(a)
    k = d.size // 2
    if d.size % 2:
        return float(np.partition(d, k)[k])
    lo, hi = np.partition(d, (k - 1, k))[k - 1:k + 1]
    return float((lo + hi) / 2.0)
