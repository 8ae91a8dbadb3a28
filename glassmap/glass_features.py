"""Per-beam input features of the glass classifiers, computed for a whole scan at once (numpy, with the
per-beam loops of the context model compiled in :mod:`glassmap.features_jit`).

Two feature sets, one per named model:

- ``baseline``: the paper's f(i, d, theta): log1p(intensity), distance (m), incidence (rad).
- ``context``: the baseline's three, then the beam's echoes (echo count, range gap last - first echo (m),
  log1p of the last echo's intensity), its neighbours along the scan (log1p intensity differences to the
  beams at -2, -1, +1, +2, the window maxima over +-3 and +-10 beams, the local range slope, the share of
  two-echo beams within +-3) and its place on its line segment (offset from the segment's middle in half
  lengths, segment length (m), the segment's mean and largest log1p intensity and two-echo share).

Intensity differences are taken to the centre beam (a neighbour without a reading counts as equal to the
centre). Values that need the second echo read as a single echo when the scan has none.
"""

from __future__ import annotations

import numpy as np

from .angles import IncidenceResult
from .beam_trig import beam_trig
from .features_jit import context_columns, segment_groups

BASELINE_FEATURES = ("log1p(intensity)", "distance_m", "incidence_rad")
CONTEXT_FEATURES = BASELINE_FEATURES + (
    "echo_count", "echo_gap_m", "log1p(last_intensity)",
    "dli_m2", "dli_m1", "dli_p1", "dli_p2", "dli_max3", "dli_max10", "range_slope_m", "two_echo_share3",
    "seg_offset", "seg_length_m", "seg_dli_mean", "seg_dli_max", "seg_two_echo_share",
)
FEATURES = {"baseline": BASELINE_FEATURES, "context": CONTEXT_FEATURES}
MODELS = tuple(FEATURES)


def scan_features(model: str, beam_angles: np.ndarray, ranges: np.ndarray, intensities: np.ndarray,
                  inc: IncidenceResult, echoes: np.ndarray | None = None,
                  echo_intensities: np.ndarray | None = None) -> np.ndarray:
    """Raw feature matrix (n, k) float32 of every beam of a scan for ``model`` (rows of beams without a
    range, intensity or incidence angle hold arbitrary finite values: select the usable beams after).

    beam_angles (n,) rad, ranges (n,) m (first echo), intensities (n,) sensor units; ``inc`` from
    :func:`glassmap.angles.incidence_angles` on the same ranges; echoes / echo_intensities: (n, e) further
    echoes (the last finite one that differs from the first echo is the beam's last echo) or None.
    """
    if model not in FEATURES:
        raise ValueError(f"unknown classifier model {model!r}; models: {', '.join(MODELS)}")
    r = np.asarray(ranges, dtype=np.float64)
    n = r.shape[0]
    i = np.asarray(intensities, dtype=np.float64)
    li = np.log1p(np.where(i > 0.0, i, 0.0))  # NaN compares False: 0
    x = np.empty((n, len(FEATURES[model])), dtype=np.float32)
    if model == "baseline":
        x[:, 0] = li
        x[:, 1] = np.where(np.isfinite(r), r, 0.0)
        a = np.abs(inc.incidence)
        x[:, 2] = np.where(a >= 0.0, a, 0.0)
        return x
    if echoes is None:
        e = lei = np.empty((n, 0))
    else:
        e = np.asarray(echoes, dtype=np.float64).reshape(n, -1)
        if echo_intensities is None:
            lei = np.empty((n, 0))
        else:
            ei = np.asarray(echo_intensities, dtype=np.float64).reshape(n, -1)
            lei = np.log1p(np.where(ei > 0.0, ei, 0.0))
    # the per-beam and per-segment loops are compiled; what they need of log1p, cos, sin and the
    # (pairwise) sums per segment is computed here
    trig = beam_trig(beam_angles)  # np.cos / np.sin of the angles, kept from the last scan with the same angles
    order, starts, li_order, ext = segment_groups(np.asarray(inc.segment, dtype=np.int64), inc.n_segments, r,
                                                  trig.cos, trig.sin, li)
    lsum = np.add.reduceat(li_order, starts) if starts.size else np.zeros(0)
    context_columns(x, li, r, np.asarray(inc.incidence, dtype=np.float64), e, lei, order, starts, lsum,
                    np.log1p(ext))
    return x
