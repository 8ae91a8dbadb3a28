"""Compiled inner loops of split-and-merge line extraction (:mod:`glassmap.angles`), numba ``njit``.

:func:`split_merge_cosines` runs the whole extraction of one scan in one call; the other kernels are its
steps. No fast-math (no fused multiply-adds), and no transcendental function but ``hypot`` and ``sqrt``:
a line's normal comes from the half-angle formulas of its covariance (:func:`tls_fit`), so the results do
not depend on which library's sin / cos / arctan2 the machine has (numpy's SIMD loops and the C library
numba calls round differently in the last bit). The final arccos stays with the caller. Points are in the
laser frame (metres); ``is_start`` marks the first point of each piece. Compiled code is cached on disk
(``cache=True``): only the first run on a machine compiles.
"""

from __future__ import annotations

import math

from .jit import njit
import numpy as np

_jit = njit(cache=True, nogil=True, error_model="numpy")  # x / 0 is inf or NaN, as in numpy


@_jit
def split_pieces(x: np.ndarray, y: np.ndarray, r: np.ndarray, is_start: np.ndarray, tol: float, tol_rel: float,
                 min_len: int, max_levels: int) -> np.ndarray:
    """Iterative end-point fit: returns a copy of ``is_start`` with every split added.

    A piece (first to last point) is split at its first farthest point from the chord when that point's
    distance exceeds its tolerance ``tol + tol_rel * r`` (m; r: the point's range) and the piece spans at least ``min_len`` points after its
    first; the two halves are fitted again, down to ``max_levels`` levels below the runs of ``is_start``.
    A chord shorter than 1e-9 m (a closed piece) measures distances to the first point."""
    n = x.shape[0]
    out = is_start.copy()
    if n == 0:
        return out
    # a stack of pieces (first, last, level): at most one piece per point is waiting at any time
    first = np.empty(n + 1, np.int64)
    last = np.empty(n + 1, np.int64)
    level = np.empty(n + 1, np.int64)
    top = 0
    end = n - 1
    for i in range(n - 1, -1, -1):
        if is_start[i]:
            first[top], last[top], level[top] = i, end, 0
            top += 1
            end = i - 1
    while top > 0:
        top -= 1
        s, e, d = first[top], last[top], level[top]
        if d >= max_levels or e - s < min_len:
            continue
        fx, fy = x[s], y[s]
        dx, dy = x[e] - fx, y[e] - fy
        length = math.hypot(dx, dy)
        best = -np.inf
        k = -1
        if length <= 1e-9:
            for i in range(s, e + 1):
                ex = math.hypot(x[i] - fx, y[i] - fy) - (tol + tol_rel * r[i])
                if ex > best:
                    best, k = ex, i
        else:
            a, b = -dy / length, dx / length
            c = -(a * fx + b * fy)
            for i in range(s, e + 1):
                ex = abs(a * x[i] + b * y[i] + c) - (tol + tol_rel * r[i])
                if ex > best:
                    best, k = ex, i
        if best > 0.0:
            out[k] = True
            first[top], last[top], level[top] = s, k - 1, d + 1
            top += 1
            first[top], last[top], level[top] = k, e, d + 1
            top += 1
    return out


@_jit
def moments(x: np.ndarray, y: np.ndarray, seg: np.ndarray, n_seg: int) -> np.ndarray:
    """Per-segment sums (n_seg, 6): count, sx, sy, sxx, syy, sxy, added in point order."""
    m = np.zeros((n_seg, 6))
    for i in range(x.shape[0]):
        s = seg[i]
        xi, yi = x[i], y[i]
        m[s, 0] += 1.0
        m[s, 1] += xi
        m[s, 2] += yi
        m[s, 3] += xi * xi
        m[s, 4] += yi * yi
        m[s, 5] += xi * yi
    return m


@_jit
def segment_keep(x: np.ndarray, y: np.ndarray, seg: np.ndarray, mom: np.ndarray, cen: np.ndarray,
                 normals: np.ndarray, rms: np.ndarray, min_points: int, min_length: float,
                 max_rms: float) -> np.ndarray:
    """Whether each segment (of its moments ``mom``, TLS centroid, normal and rms) is good enough to give
    angles: at least ``min_points`` points, ``min_length`` (m) between its extreme points along its line
    (direction (n_y, -n_x)) and an rms distance within ``max_rms`` (m)."""
    k = cen.shape[0]
    lo = np.full(k, np.inf)
    hi = np.full(k, -np.inf)
    for i in range(x.shape[0]):
        s = seg[i]
        t = (x[i] - cen[s, 0]) * normals[s, 1] - (y[i] - cen[s, 1]) * normals[s, 0]
        lo[s] = min(lo[s], t)
        hi[s] = max(hi[s], t)
    keep = np.empty(k, np.bool_)
    for s in range(k):
        keep[s] = mom[s, 0] >= min_points and hi[s] - lo[s] >= min_length and rms[s] <= max_rms
    return keep


@_jit
def _distance_for(dx: float, dy: float, thr: float) -> float:
    """``math.hypot(dx, dy)``, or a stand-in that compares with ``thr`` the same way (``>`` and ``<=``): inf or 0
    when the squared distance is off ``thr^2`` by a relative 1e-9, far beyond the rounding of the squares
    and of hypot (within an ulp), so that most comparisons need no hypot."""
    if thr >= 1e-145:  # thr^2 a normal number (or inf), and thr not NaN
        q = dx * dx + dy * dy
        t2 = thr * thr
        if q > t2 * (1.0 + 1e-9):
            return np.inf
        if q < t2 * (1.0 - 1e-9):
            return 0.0
    return math.hypot(dx, dy)


@_jit
def breaks(idx: np.ndarray, r: np.ndarray, x: np.ndarray, y: np.ndarray, dphi: float, sin_lambda: float,
           sigma3: float, max_gap: int) -> np.ndarray:
    """bool (m,): point i starts a new run (adaptive breakpoint detector): it is more than ``max_gap``
    invalid beams after the previous point, or farther from it than ``min(r) * gap * dphi / sin_lambda +
    sigma3`` (m; gap in beams)."""
    m = idx.shape[0]
    brk = np.ones(m, np.bool_)
    for i in range(1, m):
        gap = idx[i] - idx[i - 1]
        thr = min(r[i - 1], r[i]) * (float(gap) * dphi) / sin_lambda + sigma3
        brk[i] = gap > max_gap + 1 or _distance_for(x[i] - x[i - 1], y[i] - y[i - 1], thr) > thr
    return brk


@_jit
def piece_moments(x: np.ndarray, y: np.ndarray, is_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pieces of ``is_start`` (k of them): their first points (k,) and moments (2k - 1, 6): the k
    pieces', then the sums of adjacent pieces' (pieces 0 + 1, 1 + 2, ...)."""
    seg, k = labels(is_start)
    starts = np.empty(k, np.int64)
    for i in range(x.shape[0]):
        if is_start[i]:
            starts[seg[i]] = i
    mom = np.zeros((max(2 * k - 1, 0), 6))
    mom[:k] = moments(x, y, seg, k)
    for j in range(k - 1):
        for c in range(6):
            mom[k + j, c] = mom[j + 1, c] + mom[j, c]
    return starts, mom


@_jit
def merge_pieces(is_start: np.ndarray, starts: np.ndarray, run_start: np.ndarray, normals: np.ndarray,
                 rms: np.ndarray, cos_min: float, max_rms: float) -> np.ndarray:
    """``is_start`` without the starts of pieces merged into the previous one: same run, unit normals
    (rows of :func:`piece_moments`' fits) with |cos| above ``cos_min`` and a joint rms within ``max_rms``."""
    k = starts.shape[0]
    out = is_start.copy()
    for i in range(k - 1):
        c = abs(normals[i + 1, 0] * normals[i, 0] + normals[i + 1, 1] * normals[i, 1])
        if not run_start[starts[i + 1]] and c > cos_min and rms[k + i] <= max_rms:
            out[starts[i + 1]] = False
    return out


@_jit
def labels(is_start: np.ndarray) -> tuple[np.ndarray, int]:
    """Segment label of every point (the number of starts up to it, minus one) and the number of segments."""
    seg = np.empty(is_start.shape[0], np.int64)
    s = -1
    for i in range(is_start.shape[0]):
        if is_start[i]:
            s += 1
        seg[i] = s
    return seg, s + 1


@_jit
def adopt_fits(mom: np.ndarray, cen: np.ndarray, normals: np.ndarray, keep: np.ndarray, mom1: np.ndarray,
               cen1: np.ndarray, normals1: np.ndarray, keep1: np.ndarray) -> None:
    """In place: the segments kept by the first pass (``keep1``, the first ``keep1.size`` ids) take their
    first-pass fits and stay kept."""
    for s in range(keep1.shape[0]):
        if keep1[s]:
            mom[s] = mom1[s]
            cen[s] = cen1[s]
            normals[s] = normals1[s]
            keep[s] = True


@_jit
def point_cosines(ux: np.ndarray, uy: np.ndarray, idx: np.ndarray, seg: np.ndarray, keep: np.ndarray,
                  normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the points on kept segments: their beam (``idx``), |cos| of the angle between the beam
    direction (ux, uy) and the segment normal, and the segment's id among the kept ones."""
    new_id, _ = labels(keep)
    m = 0
    for i in range(seg.shape[0]):
        if keep[seg[i]]:
            m += 1
    at = np.empty(m, np.int64)
    cosang = np.empty(m)
    sid = np.empty(m, np.int64)
    m = 0
    for i in range(seg.shape[0]):
        s = seg[i]
        if keep[s]:
            at[m] = idx[i]
            cosang[m] = abs(ux[i] * normals[s, 0] + uy[i] * normals[s, 1])
            sid[m] = new_id[s]
            m += 1
    return at, cosang, sid


@_jit
def chain_points(x: np.ndarray, y: np.ndarray, r: np.ndarray, beam: np.ndarray, seg: np.ndarray,
                 keep: np.ndarray, k: float, sigma3: float, max_lag: int,
                 min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The second pass's chains over the leftover points (those on segments not in ``keep``, in scan
    order): each links to the nearest earlier leftover point up to ``max_lag`` leftover points back that
    lies within ``min(r_i, r_j) * (beam_i - beam_j) * k + sigma3`` (m); a chain is a tree of links.
    Returns (left: the leftover points, pts: the points of chains of at least ``min_points`` points, chain
    by chain (chains by their first point, points in scan order), brk: bool start mask of the chains over
    pts)."""
    n = x.shape[0]
    m = 0
    for i in range(n):
        if not keep[seg[i]]:
            m += 1
    left = np.empty(m, np.int64)
    m = 0
    for i in range(n):
        if not keep[seg[i]]:
            left[m] = i
            m += 1
    root = np.arange(m)
    for i in range(1, m):
        p = left[i]
        for lag in range(1, min(max_lag, i) + 1):
            j = i - lag
            q = left[j]
            thr = min(r[p], r[q]) * float(beam[p] - beam[q])
            thr *= k
            thr += sigma3
            if _distance_for(x[p] - x[q], y[p] - y[q], thr) <= thr:
                root[i] = root[j]
                break
    size = np.zeros(m, np.int64)
    for i in range(m):
        size[root[i]] += 1
    offset = np.zeros(m, np.int64)
    total = 0
    for i in range(m):  # roots in increasing order
        if size[i] >= min_points:
            offset[i] = total
            total += size[i]
    pts = np.empty(total, np.int64)
    brk = np.zeros(total, np.bool_)
    fill = offset.copy()
    for i in range(m):
        q = root[i]
        if size[q] >= min_points:
            if fill[q] == offset[q]:
                brk[fill[q]] = True
            pts[fill[q]] = left[i]
            fill[q] += 1
    return left, pts, brk


@_jit
def relabel(seg: np.ndarray, pts: np.ndarray, is_start: np.ndarray, first: int) -> tuple[np.ndarray, int]:
    """A copy of ``seg`` with the points ``pts`` labelled by the pieces of ``is_start`` (over pts), the
    first piece ``first``; and the number of segments then."""
    out = seg.copy()
    s = first - 1
    for i in range(pts.shape[0]):
        if is_start[i]:
            s += 1
        out[pts[i]] = s
    return out, s + 1


@_jit
def _nonneg(v: float) -> float:
    """np.maximum(v, 0.0): v unless v < 0."""
    return v if v >= 0.0 or v != v else 0.0


@_jit
def tls_moments(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least squares from moments (k, 6) up to the line direction: centroids (k, 2) m, the arguments
    (2, k) of the direction's arctan2 (2 c_xy, c_xx - c_yy; m^2) and the rms distance (k,) m of the points
    from their line (square root of the covariance's smaller eigenvalue)."""
    k = m.shape[0]
    cen = np.empty((k, 2))
    args = np.empty((2, k))
    rms = np.empty(k)
    for s in range(k):
        n = max(m[s, 0], 1.0)
        mx, my = m[s, 1] / n, m[s, 2] / n
        cxx = m[s, 3] / n - mx * mx
        cyy = m[s, 4] / n - my * my
        cxy = m[s, 5] / n - mx * my
        cen[s, 0], cen[s, 1] = mx, my
        args[0, s] = 2.0 * cxy
        args[1, s] = cxx - cyy
        tr = cxx + cyy
        det = cxx * cyy
        det -= cxy * cxy
        disc = 0.25 * tr
        disc *= tr
        disc -= det
        lam_min = 0.5 * tr
        lam_min -= math.sqrt(_nonneg(disc))
        rms[s] = math.sqrt(_nonneg(lam_min))
    return cen, args, rms


@_jit
def _half_angle_normal(a: float, b: float) -> tuple[float, float]:
    """(-sin phi, cos phi) for phi = arctan2(a, b) / 2 in [-pi/2, pi/2]: the unit normal of a line whose
    direction is phi, from cos 2phi = b / R and sin 2phi = a / R (R = hypot(a, b)) without trigonometry.
    a = b = 0 (no direction) gives phi = 0."""
    rr = math.hypot(a, b)
    if rr == 0.0:
        return -0.0, 1.0
    if b >= 0.0:
        c = math.sqrt(0.5 * (1.0 + b / rr))
        return -(a / rr) / (2.0 * c), c
    sn = math.sqrt(0.5 * (1.0 - b / rr))
    if a < 0.0 or (a == 0.0 and math.copysign(1.0, a) < 0.0):
        sn = -sn
    return -sn, (a / rr) / (2.0 * sn)


@_jit
def tls_fit(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least squares lines from moments (k, 6): centroids (k, 2) m, unit normals (k, 2) and the rms
    distance (k,) m of the points from their line."""
    cen, args, rms = tls_moments(m)
    normals = np.empty_like(cen)
    for s in range(cen.shape[0]):
        normals[s, 0], normals[s, 1] = _half_angle_normal(args[0, s], args[1, s])
    return cen, normals, rms


@_jit
def _merge(x: np.ndarray, y: np.ndarray, is_start: np.ndarray, run_start: np.ndarray, cos_min: float,
           max_rms: float) -> np.ndarray:
    """Merge neighbouring pieces of one run whose directions agree (|cos| of their normals above
    ``cos_min``) and whose joint fit stays within ``max_rms`` (m), decided pairwise for all pieces at once."""
    starts, mom = piece_moments(x, y, is_start)
    if starts.shape[0] < 2:
        return is_start
    _, normals, rms = tls_fit(mom)  # the pieces, then adjacent pairs
    return merge_pieces(is_start, starts, run_start, normals, rms, cos_min, max_rms)


@_jit
def segment_quality(x: np.ndarray, y: np.ndarray, seg: np.ndarray, n_seg: int, min_points: int, min_length: float,
                    max_rms: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per segment: moments, centroid, normal and whether it is good enough to give angles."""
    mom = moments(x, y, seg, n_seg)
    cen, normals, rms = tls_fit(mom)
    return mom, cen, normals, segment_keep(x, y, seg, mom, cen, normals, rms, min_points, min_length, max_rms)


@_jit
def split_merge_cosines(cos_a: np.ndarray, sin_a: np.ndarray, ranges: np.ndarray, max_range: float, dphi: float,
                        sin_lambda: float, sigma3: float, max_gap: int, tol: float, tol_rel: float,
                        max_levels: int, cos_merge: float, link_lag: int, min_points: int, min_length: float,
                        max_rms: float):
    """Split-and-merge of one scan (beam directions ``cos_a``, ``sin_a``, ``ranges`` m; points with a range
    in (0, ``max_range``] are used; parameters as in :class:`glassmap.angles.AngleParams`, ``dphi`` the
    beam spacing in rad).

    Breakpoints cut runs; each run is split by the iterative end-point fit and adjacent collinear pieces
    are merged; when ``link_lag`` > 0 the points of segments too poor to give angles are chained
    (:func:`chain_points`) and split and merged again, the first pass's good segments keeping their fits.
    Returns, for the points on good segments: their beam and |cos| of the angle between beam and normal,
    clipped to [0, 1]; per beam (n,) its good segment's id among the good ones (-1: none); and the good
    segments' normals (k, 2), centroids (k, 2) m and point counts (k,)."""
    m = 0
    for i in range(ranges.shape[0]):
        if ranges[i] > 0.0 and ranges[i] <= max_range:  # False for NaN; inf > max_range
            m += 1
    idx = np.empty(m, np.int64)
    m = 0
    for i in range(ranges.shape[0]):
        if ranges[i] > 0.0 and ranges[i] <= max_range:
            idx[m] = i
            m += 1
    segment = np.full(ranges.shape[0], -1, np.int64)
    if m < min_points:
        return np.empty(0, np.int64), np.empty(0), segment, np.empty((0, 2)), np.empty((0, 2)), np.empty(0, np.int64)
    ux, uy, r = cos_a[idx], sin_a[idx], ranges[idx]
    x = ux * r
    y = uy * r
    min_len = max(min_points, 3) - 1  # a piece with fewer points cannot yield a segment: never split it
    run_start = breaks(idx, r, x, y, dphi, sin_lambda, sigma3, max_gap)
    pieces = split_pieces(x, y, r, run_start, tol, tol_rel, min_len, max_levels)
    seg, n_seg = labels(_merge(x, y, pieces, run_start, cos_merge, max_rms))
    mom, cen, normals, keep = segment_quality(x, y, seg, n_seg, min_points, min_length, max_rms)
    if link_lag > 0:
        left, pts, brk = chain_points(x, y, r, idx, seg, keep, dphi / sin_lambda, sigma3, link_lag, min_points)
        if left.shape[0] >= min_points and pts.shape[0] > 0:
            px, py, pr = x[pts], y[pts], r[pts]
            pieces = split_pieces(px, py, pr, brk, tol, tol_rel, min_len, max_levels)
            seg, n_seg = relabel(seg, pts, _merge(px, py, pieces, brk, cos_merge, max_rms), n_seg)
            # only the segments with points in ``left`` changed; the others keep their first fits
            mom2, cen2, normals2, keep2 = segment_quality(x[left], y[left], seg[left], n_seg, min_points,
                                                          min_length, max_rms)
            adopt_fits(mom2, cen2, normals2, keep2, mom, cen, normals, keep)
            mom, cen, normals, keep = mom2, cen2, normals2, keep2
    at, cosang, sid = point_cosines(ux, uy, idx, seg, keep, normals)
    for i in range(at.shape[0]):
        if cosang[i] > 1.0:  # np.clip(cosang, 0, 1): |cos| >= 0 (or NaN)
            cosang[i] = 1.0
        segment[at[i]] = sid[i]
    k = 0
    for s in range(n_seg):
        if keep[s]:
            k += 1
    out_n = np.empty((k, 2))
    out_c = np.empty((k, 2))
    counts = np.empty(k, np.int64)
    k = 0
    for s in range(n_seg):
        if keep[s]:
            out_n[k] = normals[s]
            out_c[k] = cen[s]
            counts[k] = np.int64(mom[s, 0])
            k += 1
    return at, cosang, segment, out_n, out_c, counts
