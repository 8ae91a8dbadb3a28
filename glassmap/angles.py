"""Incidence angles of laser beams from straight lines in the scan (docs/method.md section 2).

The incidence angle of beam k is the angle between the beam direction and the normal of the line segment
its end point lies on, in [0, pi/2] rad. Everything is in the laser frame (metres, radians). Beams whose end
point lies on no segment get NaN. Two line extractors, both returning per-beam segment labels:

- ``"split-merge"``: breakpoints (range jumps, adaptive threshold) cut the scan into runs; each run is split
  at its farthest point from the chord until every point is within tolerance (iterative end-point fit,
  vectorized over all runs at once); adjacent collinear pieces are merged; a second pass does the same on
  the points of the pieces that were too short, chained to near earlier points across gaps (so that glass
  returns interleaved with beams passing through the pane join their pane's line); each segment gets a total least squares fit
  (moments via bincount).
- ``"hough"``: the scan points are rasterised and scikit-image's Hough transform finds lines; points within
  a tolerance of a line are split into SEGMENTS along it (scan order, gaps break a segment), so a point is
  only given a line it actually lies on, not the infinite extension of a neighbouring wall; each segment is
  then refined by least squares and a point on several segments takes the nearest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

AngleMethod = Literal["split-merge", "hough"]
METHODS: tuple[str, ...] = ("split-merge", "hough")


@dataclass(frozen=True)
class AngleParams:
    """Line extraction parameters (metres, radians, counts).

    min_points / min_length: smallest segment that yields angles. max_rms: largest TLS residual (m).
    break_lambda, break_sigma: adaptive breakpoint detector (Borges & Aldon): consecutive points farther
    apart than r * dphi / sin(break_lambda) + 3 * break_sigma start a new run. max_index_gap: a run may
    skip at most this many invalid beams. split_tol + split_tol_rel * range: end-point-fit tolerance (m).
    merge_angle: adjacent pieces whose directions differ less are merged if the joint fit stays good.
    link_lag: the second pass over the points of too-short pieces links each point to an earlier one up
    to this many leftover points back (0 = no second pass), see ``_second_pass``.
    hough_*: rasterisation cell (m), number of angle bins over 180 deg, minimum votes, maximum number of
    lines, point-to-line tolerance (m), and the gap (m) that ends a segment along a line.
    """

    min_points: int = 6
    min_length: float = 0.10
    max_rms: float = 0.03
    break_lambda: float = math.radians(10.0)
    break_sigma: float = 0.01
    max_index_gap: int = 3
    split_tol: float = 0.03
    split_tol_rel: float = 0.004
    merge_angle: float = math.radians(3.0)
    link_lag: int = 8
    max_split_iterations: int = 30
    hough_resolution: float = 0.04
    hough_angles: int = 360
    hough_threshold: int = 8
    hough_max_lines: int = 40
    hough_tol: float = 0.05
    hough_gap: float = 0.3
    max_range: float = 30.0


@dataclass
class IncidenceResult:
    """Per-beam result: ``incidence`` (n,) rad in [0, pi/2] or NaN; ``segment`` (n,) int segment id or -1;
    per segment: ``normals`` (m, 2) unit normals, ``centroids`` (m, 2) m, ``counts`` (m,) points."""

    incidence: np.ndarray
    segment: np.ndarray
    normals: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray

    @property
    def n_segments(self) -> int:
        return int(self.normals.shape[0])


def _moments(xy: np.ndarray, seg: np.ndarray, n_seg: int) -> np.ndarray:
    """Per-segment sums (n_seg, 6): count, sx, sy, sxx, syy, sxy."""
    x, y = xy[:, 0], xy[:, 1]
    m = np.empty((n_seg, 6))
    for j, w in enumerate((None, x, y, x * x, y * y, x * y)):
        m[:, j] = np.bincount(seg, w, minlength=n_seg)
    return m


def _tls(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least squares lines from moments (k, 6): centroids (k, 2), unit normals (k, 2), rms (k,) m."""
    n = np.maximum(m[:, 0], 1.0)
    q = m[:, 1:] / n[:, None]  # mean x, mean y, sxx / n, syy / n, sxy / n
    cen = q[:, :2]
    cov = q[:, 2:]
    cov -= cen[:, _COV_A] * cen[:, _COV_B]  # cxx, cyy, cxy
    cxx, cyy, cxy = cov[:, 0], cov[:, 1], cov[:, 2]
    phi = np.arctan2(2.0 * cxy, cxx - cyy)
    phi *= 0.5  # direction of the line
    normals = np.empty_like(cen)
    np.sin(phi, out=normals[:, 0])
    normals[:, 0] *= -1.0
    np.cos(phi, out=normals[:, 1])
    tr = cxx + cyy
    det = cxx * cyy
    det -= cxy * cxy
    disc = 0.25 * tr
    disc *= tr
    disc -= det
    lam_min = 0.5 * tr
    lam_min -= np.sqrt(np.maximum(disc, 0.0, out=disc), out=disc)
    return cen, normals, np.sqrt(np.maximum(lam_min, 0.0, out=lam_min), out=lam_min)


_COV_A, _COV_B = np.array([0, 1, 0]), np.array([0, 1, 1])  # columns of the products mx mx, my my, mx my


def _valid_points(beam_angles: np.ndarray, ranges: np.ndarray, max_range: float):
    a = np.asarray(beam_angles, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    if a.shape != r.shape or a.ndim != 1:
        raise ValueError(f"beam angles {a.shape} and ranges {r.shape} must be equal 1-D shapes")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r <= max_range)
    idx = valid.nonzero()[0]
    u = np.empty((idx.size, 2))
    np.cos(a[idx], out=u[:, 0])
    np.sin(a[idx], out=u[:, 1])
    return a, r, idx, u, u * r[idx, None]


def _breaks(idx: np.ndarray, r: np.ndarray, xy: np.ndarray, dphi: float, p: AngleParams) -> np.ndarray:
    """bool (m,): point i starts a new run (adaptive breakpoint detector)."""
    brk = np.ones(len(idx), dtype=bool)
    if len(idx) > 1:
        gap = np.diff(idx)
        d = np.hypot(*(xy[1:] - xy[:-1]).T)
        rr = np.minimum(r[:-1], r[1:])
        thr = rr * (gap * dphi) / math.sin(p.break_lambda) + 3.0 * p.break_sigma
        brk[1:] = (gap > p.max_index_gap + 1) | (d > thr)
    return brk


_COMPRESS_MIN = 256
"""The end-point fit drops the points of finished pieces from its arrays only while more than this many
points are left: below it an array operation costs about the same whatever the length, and dropping them
would cost five more operations per level."""


def _split(xy: np.ndarray, r: np.ndarray, starts_mask: np.ndarray, p: AngleParams) -> np.ndarray:
    """Iterative end-point fit on all runs at once. Returns the final start mask.

    The loop runs once per split level (a handful), each iteration a fixed number of array operations, so
    the cost is per operation rather than per point: ndarray methods and ``take`` with index arrays where
    they do the same as fancy indexing or boolean masks, more cheaply. A piece that is not split keeps its
    chord and is never split later; its points are dropped while many points are left (``_COMPRESS_MIN``).
    The farthest point of a piece is never its first one (distance 0, tolerance >= 0), so every level
    adds a start inside each piece it splits."""
    is_start = starts_mask.copy()
    pts = np.arange(len(xy))
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    tol = p.split_tol + p.split_tol_rel * r
    min_len = max(p.min_points, 3) - 1  # a piece with fewer points cannot yield a segment: never split it
    for _ in range(p.max_split_iterations):
        n = pts.size
        if n == 0:
            break
        sub_start = is_start.take(pts)
        seg = sub_start.cumsum()
        seg -= 1
        starts = sub_start.nonzero()[0]
        ends = np.empty_like(starts)
        ends[:-1] = starts[1:]
        ends[-1] = n
        ends -= 1
        # per piece: the chord from its first to its last point as a x + b y + c = 0 (unit normal (a, b))
        fx, fy = x.take(starts), y.take(starts)
        dx, dy = x.take(ends) - fx, y.take(ends) - fy
        length = np.hypot(dx, dy)
        degenerate = length <= 1e-9 if length.min() <= 1e-9 else None
        if degenerate is not None:
            length[degenerate] = 1.0
        a, b = -dy / length, dx / length
        c = -(a * fx + b * fy)
        dist = a.take(seg) * x
        dist += b.take(seg) * y
        dist += c.take(seg)
        dist = np.abs(dist, out=dist)
        if degenerate is not None:  # a closed piece: distance to its first point
            dg = degenerate[seg].nonzero()[0]
            dist[dg] = np.hypot(x[dg] - fx[seg[dg]], y[dg] - fy[seg[dg]])
        excess = dist
        excess -= tol
        seg_max = np.maximum.reduceat(excess, starts)
        split_seg = seg_max > 0
        split_seg &= ends - starts >= min_len
        n_split = np.count_nonzero(split_seg)
        if n_split == 0:
            break
        in_split = split_seg.take(seg)
        cand = excess == seg_max.take(seg)
        cand &= in_split
        cand = cand.nonzero()[0]
        if cand.size > n_split:  # ties: the first farthest point of each piece
            cs = seg.take(cand)
            first = np.empty(cand.size, dtype=bool)
            first[0] = True
            np.not_equal(cs[1:], cs[:-1], out=first[1:])
            cand = cand[first]
        is_start[pts.take(cand)] = True
        if n > _COMPRESS_MIN:
            keep = in_split.nonzero()[0]
            pts, x, y, tol = pts.take(keep), x.take(keep), y.take(keep), tol.take(keep)
    return is_start


def _merge(xy: np.ndarray, is_start: np.ndarray, run_start: np.ndarray, p: AngleParams) -> np.ndarray:
    """Merge neighbouring pieces of one run whose directions agree within merge_angle and whose joint fit
    stays within max_rms (decided pairwise for all pieces at once)."""
    starts = np.flatnonzero(is_start)
    if len(starts) < 2:
        return is_start
    seg = np.cumsum(is_start) - 1
    k = len(starts)
    mom = _moments(xy, seg, k)
    _, normals, rms = _tls(np.concatenate((mom, mom[1:] + mom[:-1])))  # the pieces, then adjacent pairs
    normals, joint_rms = normals[:k], rms[k:]
    cos = np.abs(np.einsum("ij,ij->i", normals[1:], normals[:-1]))
    ok = ~run_start[starts[1:]] & (cos > math.cos(p.merge_angle)) & (joint_rms <= p.max_rms)
    out = is_start.copy()
    out[starts[1:][ok]] = False
    return out


def _finish(n: int, idx: np.ndarray, u: np.ndarray, xy: np.ndarray, seg: np.ndarray, n_seg: int,
            p: AngleParams, drop_last: bool = False, quality: tuple | None = None) -> IncidenceResult:
    """Fit every segment (unless ``quality``, the result of :func:`_quality` for these segments, is given),
    keep the good ones, and compute per-beam incidence angles."""
    incidence = np.full(n, np.nan)
    segment = np.full(n, -1, dtype=np.int64)
    if n_seg == 0 or len(idx) == 0:
        return IncidenceResult(incidence, segment, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    mom, cen, normals, keep = _quality(xy, seg, n_seg, p) if quality is None else quality
    if drop_last:
        keep[-1] = False  # the bucket of points on no segment
    new_id = np.cumsum(keep) - 1
    on = keep.take(seg).nonzero()[0]
    s = seg.take(on)
    cosang = u[:, 0].take(on) * normals[:, 0].take(s)
    cosang += u[:, 1].take(on) * normals[:, 1].take(s)
    np.abs(cosang, out=cosang)
    at = idx.take(on)
    incidence[at] = np.arccos(np.clip(cosang, 0.0, 1.0, out=cosang), out=cosang)
    segment[at] = new_id.take(s)
    return IncidenceResult(incidence, segment, normals[keep], cen[keep], mom[keep, 0].astype(np.int64))


def split_merge(beam_angles: np.ndarray, ranges: np.ndarray, params: AngleParams = AngleParams()) -> IncidenceResult:
    """Incidence angles from split-and-merge segments with total least squares fits."""
    a, r, idx, u, xy = _valid_points(beam_angles, ranges, params.max_range)
    n = a.shape[0]
    if len(idx) < params.min_points:
        return _finish(n, idx, u, xy, np.zeros(len(idx), dtype=np.int64), 0, params)
    dphi = float(np.median(np.diff(a))) if n > 1 else 0.0
    rv = r[idx]
    run_start = _breaks(idx, rv, xy, abs(dphi), params)
    is_start = _split(xy, rv, run_start, params)
    is_start = _merge(xy, is_start, run_start, params)
    seg = np.cumsum(is_start) - 1
    n_seg = int(is_start.sum())
    quality = None
    if params.link_lag > 0:
        quality = _quality(xy, seg, n_seg, params)
        seg, n_seg2, left = _second_pass(xy, rv, idx, abs(dphi), seg, n_seg, quality[3], params)
        if left is not None:
            quality = _requality(xy, seg, n_seg2, quality, left, params)
        n_seg = n_seg2
    return _finish(n, idx, u, xy, seg, n_seg, params, quality=quality)


def _quality(xy: np.ndarray, seg: np.ndarray, n_seg: int, p: AngleParams):
    """Per segment: moments, centroid, normal and whether it is good enough to give angles."""
    mom = _moments(xy, seg, n_seg)
    cen, normals, rms = _tls(mom)
    # coordinate along the segment's direction
    along = xy[:, 0] - cen[:, 0].take(seg)
    along *= normals[:, 1].take(seg)
    along -= (xy[:, 1] - cen[:, 1].take(seg)) * normals[:, 0].take(seg)
    lo = np.full(n_seg, np.inf)
    hi = np.full(n_seg, -np.inf)
    np.minimum.at(lo, seg, along)
    np.maximum.at(hi, seg, along)
    keep = (mom[:, 0] >= p.min_points) & (hi - lo >= p.min_length) & (rms <= p.max_rms)
    return mom, cen, normals, keep


def _requality(xy: np.ndarray, seg: np.ndarray, n_seg: int, first: tuple, left: np.ndarray, p: AngleParams):
    """:func:`_quality` after the second pass, fitting only the segments with points in ``left`` (the
    points of the first pass's rejected segments); the first pass's good segments keep their fits, which
    are the same numbers (bincount adds each segment's points in the same order)."""
    mom, cen, normals, keep = _quality(xy[left], seg.take(left), n_seg, p)
    kept = first[3].nonzero()[0]
    mom[kept], cen[kept], normals[kept], keep[kept] = first[0][kept], first[1][kept], first[2][kept], True
    return mom, cen, normals, keep


def _second_pass(xy: np.ndarray, r: np.ndarray, idx: np.ndarray, dphi: float, seg: np.ndarray, n_seg: int,
                 keep: np.ndarray, p: AngleParams) -> tuple[np.ndarray, int, np.ndarray | None]:
    """Split-and-merge again on the points of the pieces that were too short.

    Glass returns come in short fragments interleaved with beams that passed through the pane (which range
    an object behind it, itself fragmented). Each leftover point links to the nearest earlier leftover
    point (up to ``link_lag`` points back) that is as close as a breakpoint-free neighbour would be for
    that beam gap; the resulting chains (roots by pointer jumping) are split and merged like runs. All
    vectorized over points; the loop runs over pointer-jumping steps. ``keep``: the first pass's good
    segments. Returns the segment labels, their number and the points whose segment may have changed
    (None: none did).
    """
    left = (~keep[seg]).nonzero()[0]
    m = left.size
    if m < p.min_points:
        return seg, n_seg, None
    sx, sr, si = xy[left], r[left], idx[left]
    ar = np.arange(m)
    parent = ar.copy()
    k = dphi / math.sin(p.break_lambda)
    # all lags at once: (m, lags) candidate earlier points j = i - lag; a point links to the nearest one
    lags = np.arange(1, min(p.link_lag, m - 1) + 1)
    j = ar[:, None] - lags
    before = j >= 0
    np.maximum(j, 0, out=j)
    gx, gy = sx[:, 0].copy(), sx[:, 1].copy()
    d = np.hypot(gx[:, None] - gx.take(j), gy[:, None] - gy.take(j))
    thr = np.minimum(sr[:, None], sr.take(j))
    thr *= si[:, None] - si.take(j)
    thr *= k
    thr += 3.0 * p.break_sigma
    link = d <= thr
    link &= before
    nearest = link.argmax(axis=1)
    linked = link[ar, nearest]
    parent[linked] = ar[linked] - lags[nearest[linked]]
    for _ in range(32):
        pp = parent[parent]
        if (pp == parent).all():
            break
        parent = pp
    # chains shorter than min_points cannot give a segment: leave them out
    big = np.bincount(parent, minlength=m)[parent] >= p.min_points
    if not big.any():
        return seg, n_seg, None
    order = big.nonzero()[0]
    order = order[np.argsort(parent[order], kind="stable")]
    root = parent[order]
    m = order.size
    brk = np.ones(m, dtype=bool)
    brk[1:] = root[1:] != root[:-1]
    px, pr = sx[order], sr[order]
    is2 = _merge(px, _split(px, pr, brk, p), brk, p)
    seg = seg.copy()
    seg[left[order]] = n_seg + np.cumsum(is2) - 1
    return seg, n_seg + int(is2.sum()), left


def hough(beam_angles: np.ndarray, ranges: np.ndarray, params: AngleParams = AngleParams()) -> IncidenceResult:
    """Incidence angles from scikit-image Hough lines, with points assigned to segments along the lines."""
    from skimage.transform import hough_line, hough_line_peaks

    p = params
    a, r, idx, u, xy = _valid_points(beam_angles, ranges, p.max_range)
    n = a.shape[0]
    if len(idx) < p.min_points:
        return _finish(n, idx, u, xy, np.zeros(len(idx), dtype=np.int64), 0, p)
    res = p.hough_resolution
    lo = xy.min(axis=0)
    pix = np.floor((xy - lo) / res).astype(np.int64)
    shape = (int(pix[:, 1].max()) + 1, int(pix[:, 0].max()) + 1)
    img = np.zeros(shape, dtype=bool)
    img[pix[:, 1], pix[:, 0]] = True
    thetas = np.linspace(-np.pi / 2, np.pi / 2, p.hough_angles, endpoint=False)
    acc, ang, dist = hough_line(img, theta=thetas)
    _, lt, ld = hough_line_peaks(acc, ang, dist, min_distance=max(1, int(round(p.hough_tol / res))),
                                 min_angle=max(1, p.hough_angles // 90), threshold=p.hough_threshold,
                                 num_peaks=p.hough_max_lines)
    if len(lt) == 0:
        return _finish(n, idx, u, xy, np.zeros(len(idx), dtype=np.int64), 0, p)
    # pixel-space line x cos t + y sin t = d (x = column, y = row, pixel centres at integer coordinates)
    # -> metric: X cos t + Y sin t = rho with X = lo_x + (x + 0.5) res
    nrm = np.stack([np.cos(lt), np.sin(lt)], axis=1)
    rho = ld * res + (lo + 0.5 * res) @ nrm.T
    dist_pl = np.abs(xy @ nrm.T - rho[None, :])  # (m, L)
    near = dist_pl <= p.hough_tol
    # segments along each line: candidate points in scan order, split at spatial gaps
    seg_of = np.full(dist_pl.shape, -1, dtype=np.int64)
    n_seg = 0
    for j in range(len(lt)):  # loop over lines (tens), not beams
        c = np.flatnonzero(near[:, j])
        if c.size < p.min_points:
            continue
        gaps = np.hypot(*(xy[c[1:]] - xy[c[:-1]]).T) > p.hough_gap
        sid = np.concatenate([[0], np.cumsum(gaps)])
        cnt = np.bincount(sid)
        good = cnt[sid] >= p.min_points
        if not good.any():
            continue
        _, ids = np.unique(sid[good], return_inverse=True)
        seg_of[c[good], j] = n_seg + ids
        n_seg += int(ids.max()) + 1
    if n_seg == 0:
        return _finish(n, idx, u, xy, np.zeros(len(idx), dtype=np.int64), 0, p)
    # least-squares refinement of each segment, then each point takes its nearest segment
    rows, cols = np.nonzero(seg_of >= 0)
    sids = seg_of[rows, cols]
    mom = _moments(xy[rows], sids, n_seg)
    cen, normals, _ = _tls(mom)
    d_ref = np.abs(np.einsum("ij,ij->i", xy[rows] - cen[sids], normals[sids]))
    on = d_ref <= p.hough_tol
    rows, sids, d_ref = rows[on], sids[on], d_ref[on]
    # a point on several segments takes the best supported one (most points), then the nearest; short
    # segments through a corner would otherwise steal the corner points
    order = np.lexsort((d_ref, -mom[sids, 0], rows))
    rows, sids = rows[order], sids[order]
    first = np.ones(len(rows), dtype=bool)
    first[1:] = rows[1:] != rows[:-1]
    seg = np.full(len(idx), n_seg, dtype=np.int64)  # n_seg = "no segment" bucket, dropped below
    seg[rows[first]] = sids[first]
    return _finish(n, idx, u, xy, seg, n_seg + 1, p, drop_last=True)


def incidence_angles(beam_angles: np.ndarray, ranges: np.ndarray, method: AngleMethod = "split-merge",
                     params: AngleParams = AngleParams()) -> IncidenceResult:
    """Per-beam incidence angles (rad, NaN where the end point lies on no segment).

    beam_angles: (n,) rad in the laser frame; ranges: (n,) m (NaN / inf / out of range = no point).
    """
    if method == "split-merge":
        return split_merge(beam_angles, ranges, params)
    if method == "hough":
        return hough(beam_angles, ranges, params)
    raise ValueError(f"unknown angle method {method!r}; choose one of {', '.join(METHODS)}")
