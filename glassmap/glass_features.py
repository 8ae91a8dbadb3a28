"""Per-beam input features of the glass classifiers, computed for a whole scan at once (vectorized).

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

BASELINE_FEATURES = ("log1p(intensity)", "distance_m", "incidence_rad")
CONTEXT_FEATURES = BASELINE_FEATURES + (
    "echo_count", "echo_gap_m", "log1p(last_intensity)",
    "dli_m2", "dli_m1", "dli_p1", "dli_p2", "dli_max3", "dli_max10", "range_slope_m", "two_echo_share3",
    "seg_offset", "seg_length_m", "seg_dli_mean", "seg_dli_max", "seg_two_echo_share",
)
FEATURES = {"baseline": BASELINE_FEATURES, "context": CONTEXT_FEATURES}
MODELS = tuple(FEATURES)


_PAD = 10  # beams of padding on each side of the scan (the widest neighbourhood)


def _padded(a: np.ndarray, fill: float) -> np.ndarray:
    """``a`` with _PAD values ``fill`` on each side: element i of the scan is at i + _PAD."""
    out = np.full(a.shape[0] + 2 * _PAD, fill)
    out[_PAD:_PAD + a.shape[0]] = a
    return out


def _window7(n: int) -> np.ndarray:
    """Beams in [i - 3, i + 3] inside a scan of n beams."""
    i = np.arange(n)
    return (np.minimum(i + 4, n) - np.maximum(i - 3, 0)).astype(np.float64)


_WINDOW7 = {1081: _window7(1081)}


def _running_max(pad: np.ndarray, w: int, n: int) -> np.ndarray:
    """max(a[i - w .. i + w]) for i < n from ``_padded(a, -inf)`` (w <= _PAD), by doubling windows."""
    m, width = pad, 1
    while 2 * width <= 2 * w + 1:
        m = np.maximum(m[:-width], m[width:])  # m[j] = max(pad[j .. j + 2 width - 1])
        width *= 2
    rest = 2 * w + 1 - width
    if rest:
        m = np.maximum(m[:-rest], m[rest:])
    return m[_PAD - w:_PAD - w + n]


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
    ok_r = np.isfinite(r)
    i = np.asarray(intensities, dtype=np.float64)
    li = np.log1p(np.where(i > 0.0, i, 0.0))  # NaN compares False: 0
    k = len(FEATURES[model])
    x = np.empty((n, k), dtype=np.float32)
    x[:, 0] = li
    x[:, 1] = np.where(ok_r, r, 0.0)
    a = np.abs(inc.incidence)
    x[:, 2] = np.where(a >= 0.0, a, 0.0)
    if model == "baseline":
        return x

    # echoes: the last finite extra echo beyond the first
    if echoes is not None:
        e = np.asarray(echoes, dtype=np.float64).reshape(n, -1)
        with np.errstate(invalid="ignore"):
            fin = (np.abs(e - r[:, None]) > 1e-6) & np.isfinite(e)
        two = fin.any(axis=1)
        col = e.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)
        rows = np.arange(n)
        gap = e[rows, col] - r
        x[:, 4] = np.where(two, np.minimum(np.maximum(gap, -5.0), 10.0), 0.0)
        if echo_intensities is not None:
            ei = np.asarray(echo_intensities, dtype=np.float64).reshape(n, -1)[rows, col]
            x[:, 5] = np.where(two & (ei > 0.0), np.log1p(np.where(ei > 0.0, ei, 0.0)), 0.0)
        else:
            x[:, 5] = 0.0
    else:
        two = np.zeros(n, dtype=bool)
        x[:, 4:6] = 0.0
    x[:, 3] = 1.0 + two

    # neighbours along the scan (beams without a reading count as the centre's value)
    lv = _padded(np.where(ok_r, li, np.nan), np.nan)
    for j, k in enumerate((-2, -1, 1, 2)):
        d = lv[_PAD + k:_PAD + k + n] - li
        x[:, 6 + j] = np.where(d == d, d, 0.0)
    lm = _padded(np.where(ok_r, li, -np.inf), -np.inf)
    x[:, 10] = np.maximum(_running_max(lm, 3, n), li) - li
    x[:, 11] = np.maximum(_running_max(lm, 10, n), li) - li
    rv = np.where(ok_r, r, np.nan)
    rp = np.empty(n)
    rm = np.empty(n)
    rp[:-1], rp[-1] = rv[1:], rv[-1]  # the first and last beam take themselves as the missing neighbour
    rm[1:], rm[0] = rv[:-1], rv[0]
    slope = np.abs(rp - rm) * 0.5
    x[:, 12] = np.where(slope <= 1.0, slope, 1.0)  # NaN (a neighbour without a range) -> 1
    tp = np.zeros(n + 7)
    tp[3:n + 3] = two
    c = np.cumsum(tp)  # c[j] = sum of tp[0 .. j]
    w7 = _WINDOW7.get(n)
    x[:, 13] = (c[6:n + 6] - np.concatenate(([0.0], c[:n - 1]))) / (w7 if w7 is not None else _window7(n))

    # place on the line segment (groups of beams by segment id, via one sort)
    seg = inc.segment
    x[:, 14] = 1.0
    x[:, 15:19] = 0.0
    on = np.flatnonzero(seg >= 0)
    if on.size:
        order = on[np.argsort(seg[on], kind="stable")]  # beams grouped by segment, in beam order
        s_sorted = seg[order]
        brk = np.empty(order.size, dtype=bool)
        brk[0] = True
        np.not_equal(s_sorted[1:], s_sorted[:-1], out=brk[1:])
        starts = np.flatnonzero(brk)
        ends = np.empty_like(starts)
        ends[:-1] = starts[1:]
        ends[-1] = order.size
        cnt = (ends - starts).astype(np.float64)
        grp = np.repeat(np.arange(starts.size), ends - starts)
        idx = order.astype(np.float64)
        lo_i, hi_i = idx[starts], idx[ends - 1]
        mid = 0.5 * (lo_i + hi_i)
        half = np.maximum(0.5 * (hi_i - lo_i), 0.5)
        x[order, 14] = np.abs(idx - mid[grp]) / half[grp]
        ang = beam_angles[order]
        ro = r[order]
        px, py = ro * np.cos(ang), ro * np.sin(ang)
        ext = np.hypot(np.maximum.reduceat(px, starts) - np.minimum.reduceat(px, starts),
                       np.maximum.reduceat(py, starts) - np.minimum.reduceat(py, starts))
        x[order, 15] = np.log1p(ext)[grp]
        lio = li[order]
        x[order, 16] = (np.add.reduceat(lio, starts) / cnt)[grp] - lio
        x[order, 17] = np.maximum.reduceat(lio, starts)[grp] - lio
        x[order, 18] = (np.add.reduceat(two[order].astype(np.float64), starts) / cnt)[grp]
    return x
