"""Incidence angles of laser beams from straight lines in the scan (docs/method.md section 2).

The incidence angle of beam k is the angle between the beam direction and the normal of the line segment
its end point lies on, in [0, pi/2] rad. Everything is in the laser frame (metres, radians). Beams whose end
point lies on no segment get NaN. Two line extractors, both returning per-beam segment labels:

- ``"split-merge"``: breakpoints (range jumps, adaptive threshold) cut the scan into runs; each run is split
  at its farthest point from the chord until every point is within tolerance (iterative end-point fit);
  adjacent collinear pieces are merged; a second pass does the same on
  the points of the pieces that were too short, chained to near earlier points across gaps (so that glass
  returns interleaved with beams passing through the pane join their pane's line); each segment gets a total least squares fit
  (moments summed in point order). The whole extraction is one compiled call per scan
  (:func:`glassmap.angles_jit.split_merge_cosines`).
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

from .angles_jit import moments, point_cosines, segment_quality, split_merge_cosines, tls_fit
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


def _checked(beam_angles: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angles (rad) and ranges (m) as contiguous float64 arrays of one equal 1-D shape (ValueError if not)."""
    a = np.ascontiguousarray(beam_angles, dtype=np.float64)
    r = np.ascontiguousarray(ranges, dtype=np.float64)
    if a.shape != r.shape or a.ndim != 1:
        raise ValueError(f"beam angles {a.shape} and ranges {r.shape} must be equal 1-D shapes")
    return a, r


def _valid_points(beam_angles: np.ndarray, ranges: np.ndarray, max_range: float):
    a, r = _checked(beam_angles, ranges)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r <= max_range)
    idx = valid.nonzero()[0]
    trig = beam_trig(a)  # np.cos / np.sin of the angles, kept from the last scan with the same angles
    u = np.empty((idx.size, 2))
    u[:, 0] = trig.cos[idx]
    u[:, 1] = trig.sin[idx]
    return a, r, idx, u, u * r[idx, None]


def _finish(n: int, idx: np.ndarray, u: np.ndarray, xy: np.ndarray, seg: np.ndarray, n_seg: int,
            p: AngleParams, drop_last: bool = False) -> IncidenceResult:
    """Fit every segment, keep the good ones, and compute per-beam incidence angles."""
    incidence = np.full(n, np.nan)
    segment = np.full(n, -1, dtype=np.int64)
    if n_seg == 0 or len(idx) == 0:
        return IncidenceResult(incidence, segment, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    mom, cen, normals, keep = segment_quality(x, y, seg, n_seg, p.min_points, p.min_length, p.max_rms)
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
    a, r = _checked(beam_angles, ranges)
    trig = beam_trig(a)  # np.cos / np.sin of the angles, kept from the last scan with the same angles
    at, cosang, segment, normals, cen, counts = split_merge_cosines(
        trig.cos, trig.sin, r, p.max_range, abs(trig.median_step), math.sin(p.break_lambda), 3.0 * p.break_sigma,
        p.max_index_gap, p.split_tol, p.split_tol_rel, p.max_split_iterations, math.cos(p.merge_angle), p.link_lag,
        p.min_points, p.min_length, p.max_rms)
    incidence = np.full(a.shape[0], np.nan)
    incidence[at] = np.arccos(cosang, out=cosang)
    return IncidenceResult(incidence, segment, normals, cen, counts)


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
    cen, normals, _ = tls_fit(mom)
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
