"""Incidence angles of laser beams from straight lines in the scan (docs/method.md section 2).

The incidence angle of beam k is the angle between the beam direction and the normal of the line segment
its end point lies on, in [0, pi/2] rad. Everything is in the laser frame (metres, radians). Beams whose end
point lies on no segment get NaN. Two line extractors, both returning per-beam segment labels:

- ``"split-merge"``: breakpoints (range jumps, adaptive threshold) cut the scan into runs; each run is split
  at its farthest point from the chord until every point is within tolerance (iterative end-point fit);
  adjacent collinear pieces are merged; a second pass does the same on
  the points of the pieces that were too short, chained to near earlier points across gaps (so that glass
  returns interleaved with beams passing through the pane join their pane's line); each segment gets a total least squares fit
  (moments summed in point order). The point-by-point loops are compiled (:mod:`glassmap.angles_jit`);
  the transcendental functions run in numpy.
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

from .angles_jit import (adopt_fits, breaks, chain_points, labels, merge_pieces, moments, piece_moments, point_cosines,
                         relabel, segment_keep, split_pieces, tls_moments)
from .beam_trig import beam_trig

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
    return moments(np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]), seg, n_seg)


def _tls(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least squares lines from moments (k, 6): centroids (k, 2), unit normals (k, 2), rms (k,) m."""
    cen, args, rms = tls_moments(m)
    phi = np.arctan2(args[0], args[1])
    phi *= 0.5  # direction of the line
    normals = np.empty_like(cen)
    np.sin(phi, out=normals[:, 0])
    normals[:, 0] *= -1.0
    np.cos(phi, out=normals[:, 1])
    return cen, normals, rms


def _valid_points(beam_angles: np.ndarray, ranges: np.ndarray, max_range: float):
    a = np.asarray(beam_angles, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    if a.shape != r.shape or a.ndim != 1:
        raise ValueError(f"beam angles {a.shape} and ranges {r.shape} must be equal 1-D shapes")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r <= max_range)
    idx = valid.nonzero()[0]
    trig = beam_trig(a)  # np.cos / np.sin of the angles, kept from the last scan with the same angles
    u = np.empty((idx.size, 2))
    u[:, 0] = trig.cos[idx]
    u[:, 1] = trig.sin[idx]
    return a, r, idx, u, u * r[idx, None]


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
    at, cosang, sid = point_cosines(np.ascontiguousarray(u[:, 0]), np.ascontiguousarray(u[:, 1]), idx, seg, keep,
                                    normals)
    incidence[at] = np.arccos(np.clip(cosang, 0.0, 1.0, out=cosang), out=cosang)
    segment[at] = sid
    return IncidenceResult(incidence, segment, normals[keep], cen[keep], mom[keep, 0].astype(np.int64))


def split_merge(beam_angles: np.ndarray, ranges: np.ndarray, params: AngleParams = AngleParams()) -> IncidenceResult:
    """Incidence angles from split-and-merge segments with total least squares fits."""
    p = params
    a, r, idx, u, xy = _valid_points(beam_angles, ranges, p.max_range)
    n = a.shape[0]
    if len(idx) < p.min_points:
        return _finish(n, idx, u, xy, np.zeros(len(idx), dtype=np.int64), 0, p)
    dphi = abs(beam_trig(a).median_step)
    x, y, rv = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]), r[idx]
    run_start = breaks(idx, rv, x, y, dphi, math.sin(p.break_lambda), 3.0 * p.break_sigma, p.max_index_gap)
    seg, n_seg = labels(_merge(x, y, _split(x, y, rv, run_start, p), run_start, p))
    quality = None
    if p.link_lag > 0:
        quality = _quality(xy, seg, n_seg, p)
        seg, n_seg2, left = _second_pass(x, y, rv, idx, dphi, seg, n_seg, quality[3], p)
        if left is not None:
            quality = _requality(xy, seg, n_seg2, quality, left, p)
        n_seg = n_seg2
    return _finish(n, idx, u, xy, seg, n_seg, p, quality=quality)


def _split(x: np.ndarray, y: np.ndarray, r: np.ndarray, starts_mask: np.ndarray, p: AngleParams) -> np.ndarray:
    """Iterative end-point fit on all runs at once (:func:`glassmap.angles_jit.split_pieces`). Returns the
    final start mask."""
    min_len = max(p.min_points, 3) - 1  # a piece with fewer points cannot yield a segment: never split it
    return split_pieces(x, y, r, starts_mask, p.split_tol, p.split_tol_rel, min_len, p.max_split_iterations)


def _merge(x: np.ndarray, y: np.ndarray, is_start: np.ndarray, run_start: np.ndarray, p: AngleParams) -> np.ndarray:
    """Merge neighbouring pieces of one run whose directions agree within merge_angle and whose joint fit
    stays within max_rms (decided pairwise for all pieces at once)."""
    starts, mom = piece_moments(x, y, is_start)
    if len(starts) < 2:
        return is_start
    _, normals, rms = _tls(mom)  # the pieces, then adjacent pairs
    return merge_pieces(is_start, starts, run_start, normals, rms, math.cos(p.merge_angle), p.max_rms)


def _quality(xy: np.ndarray, seg: np.ndarray, n_seg: int, p: AngleParams):
    """Per segment: moments, centroid, normal and whether it is good enough to give angles."""
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    mom = moments(x, y, seg, n_seg)
    cen, normals, rms = _tls(mom)
    return mom, cen, normals, segment_keep(x, y, seg, mom, cen, normals, rms, p.min_points, p.min_length, p.max_rms)


def _requality(xy: np.ndarray, seg: np.ndarray, n_seg: int, first: tuple, left: np.ndarray, p: AngleParams):
    """:func:`_quality` after the second pass, fitting only the segments with points in ``left`` (the
    points of the first pass's rejected segments); the first pass's good segments keep their fits, which
    are the same numbers (the moments add each segment's points in the same order)."""
    mom, cen, normals, keep = _quality(xy[left], seg.take(left), n_seg, p)
    adopt_fits(mom, cen, normals, keep, *first)
    return mom, cen, normals, keep


def _second_pass(x: np.ndarray, y: np.ndarray, r: np.ndarray, idx: np.ndarray, dphi: float, seg: np.ndarray,
                 n_seg: int, keep: np.ndarray, p: AngleParams) -> tuple[np.ndarray, int, np.ndarray | None]:
    """Split-and-merge again on the points of the pieces that were too short.

    Glass returns come in short fragments interleaved with beams that passed through the pane (which range
    an object behind it, itself fragmented). Each leftover point links to the nearest earlier leftover
    point (up to ``link_lag`` points back) that is as close as a breakpoint-free neighbour would be for
    that beam gap (:func:`glassmap.angles_jit.chain_points`); the resulting chains are split and merged
    like runs. ``keep``: the first pass's good segments. Returns the segment labels, their number and the
    points whose segment may have changed (None: none did).
    """
    left, pts, brk = chain_points(x, y, r, idx, seg, keep, dphi / math.sin(p.break_lambda), 3.0 * p.break_sigma,
                                  p.link_lag, p.min_points)
    if left.size < p.min_points or pts.size == 0:
        return seg, n_seg, None
    px, py, pr = x.take(pts), y.take(pts), r.take(pts)
    seg, n = relabel(seg, pts, _merge(px, py, _split(px, py, pr, brk, p), brk, p), n_seg)
    return seg, n, left


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
