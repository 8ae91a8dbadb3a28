"""Correlative scan-to-map matching (Olson 2009 style) with a covariance from the score distribution.

The scan's end points (base frame) are scored against a :class:`LikelihoodField` for a lattice of poses
(x, y in grid cells, yaw in steps small enough that the farthest typical point moves about one cell):
score(pose) = sum_j w_j * L(R(yaw) p_j + t). Two resolutions: the whole search window is scored at a
coarse translation step on the block-max field (an upper bound of the fine score), then the fine lattice is
scored around the best coarse candidates. All poses of one stage are scored in one vectorized gather.

Covariance: the scores are turned into a distribution pi(pose) ~ exp(beta * (score - max)),
beta = ``min(1, independent_points / sum(w))`` (end points are correlated, so the scan carries the information of
fewer independent points than it has; see ``MatcherConfig.independent_points``). Its covariance is the law
of total variance over the fine lattice's cells: the second moment of pi on the lattice (the spread between
cells, e.g. along a corridor) plus the covariance of pi inside the peak's cell, from the curvature of the
scores there (the spread within a cell: most of the covariance when the match is sharper than the 5 cm
lattice step, which the lattice alone would report as zero; see ``_within_cell_covariance``).
The measurement is the mean of pi on flat axes; where pi is curved, it is the vertex of a parabola through
the peak score and its neighbours (per axis), as the mean snaps to the lattice when pi is narrow.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from glassmap.pose.estimator_jit import warm_up as warm_up_estimator
from glassmap.pose.field import LikelihoodField
from glassmap.pose.field_jit import warm_up as warm_up_field
from glassmap.pose.filter_jit import warm_up as warm_up_filter
from glassmap.pose.matcher_jit import cell_values, scaled_squared_distances


@dataclass(frozen=True)
class MatcherConfig:
    """Search and scoring settings. Lengths in metres, angles in radians.

    range_min / range_max: beams used for matching (long beams are noisy and move most with yaw);
    voxel: end points are thinned to about one per voxel (m) of arc so that near walls do not dominate (see
        :func:`select_points`); max_points:
    then thinned by stride to at most this many; min_points: fewer usable points -> no match.
    window_sigmas: the search half-width is this many prior standard deviations, clipped to
    [xy_window_min, xy_window_max] and [yaw_window_min, yaw_window_max].
    fine_half_cells / fine_half_yaw: half-size (lattice steps) of the fine window used for the peak and the
    covariance; yaw_step_min/max: bounds of the fine yaw step; max_refine: coarse candidates refined.
    independent_points: tempering of the score distribution (see module docstring; beta is at most 1: a scan
        never counts as more independent points than it has; docs/pose.md says how the value was chosen).
    bilinear: interpolate the field bilinearly in the fine stage (smooth scores, sub-cell accuracy; four
        lookups per point): the vector to the nearest wall point when the field has vectors (exact near a
        straight wall), else the likelihood itself.
    switch_margin: a window away from the prior replaces the prior-centred one only if its peak score is
        better by this much (log-likelihood units: clearly better, not noise along a flat ridge).
    min_quality: mean end-point likelihood at the peak (0..1) below which the match is rejected.
    """

    range_min: float = 0.3
    range_max: float = 15.0
    voxel: float = 0.08
    max_points: int = 200
    min_points: int = 25
    window_sigmas: float = 3.0
    xy_window_min: float = 0.15
    xy_window_max: float = 0.5
    yaw_window_min: float = np.radians(2.0)
    yaw_window_max: float = np.radians(10.0)
    fine_half_cells: int = 3
    fine_half_yaw: int = 3
    yaw_step_min: float = np.radians(0.1)
    yaw_step_max: float = np.radians(0.25)
    max_refine: int = 1
    switch_margin: float = 2.0
    bilinear: bool = True
    independent_points: float = 120.0
    min_quality: float = 0.25


@dataclass
class MatchResult:
    """pose (3,) base in the map frame (mean of the score distribution); covariance 3x3 (m^2, rad^2);
    peak_pose (3,) the best lattice pose; quality: mean end-point likelihood at the peak (0..1);
    n_points used; n_poses scored; edge: the peak was on the border of the fine window; lever (m): the median
    range of the end points; information (3, 3): that of the end points about the pose, from
    the walls they lie on (see :meth:`CorrelativeMatcher.information` and :func:`constrained_directions`)."""

    pose: np.ndarray
    covariance: np.ndarray
    peak_pose: np.ndarray
    quality: float
    n_points: int
    n_poses: int
    edge: bool
    lever: float = 1.0
    information: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.inf))


def constrained_directions(information: np.ndarray, lever: float, sigma_hit: float, min_points: float) -> np.ndarray:
    """Rows (k, 3), k = 0..3: the directions of pose space (x, y, yaw) a match constrains.

    ``information`` is that of the end points about the pose (:meth:`CorrelativeMatcher.information`,
    untempered: one end point on a wall facing a direction gives 1 / sigma_hit^2 along it). Yaw is compared
    with translation through ``lever`` (m, the median range of the end points: a yaw change d moves them
    by about lever * d), and an eigen-direction counts as constrained when it carries the information of
    at least ``min_points`` end points squarely facing it: a single stray point at the ragged end of a
    mapped wall is not a feature, and the score's spread over the window is not a test (along a featureless
    corridor it still shows spurious peaks). The rows are mapped back to pose space; fusing only them lets
    the covariance keep growing along the others."""
    if not np.all(np.isfinite(information)) or not lever > 0:
        return np.eye(3)
    d, vals, vecs = _lever_scaled_eigen(information, lever)
    keep = vals >= min_points / sigma_hit ** 2
    return (vecs[:, keep] / d[:, None]).T


def _lever_scaled_eigen(information: np.ndarray, lever: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d, eigenvalues, eigenvectors as columns) of the information with yaw compared with translation through
    ``lever`` (m): d = (1, 1, 1 / lever) scales it to d J d."""
    d = np.array([1.0, 1.0, 1.0 / lever])
    jn = information * np.outer(d, d)
    vals, vecs = np.linalg.eigh(0.5 * (jn + jn.T))
    return d, vals, vecs


def slid_to_prior(pose: np.ndarray, prior: np.ndarray, prior_cov: np.ndarray, information: np.ndarray, lever: float,
                  sigma_hit: float, min_points: float, min_shift: float = 0.1, min_sigmas: float = 3.0,
                  max_yaw_share: float = 0.5) -> np.ndarray:
    """The match ``pose`` (3,) with its translation from ``prior`` (3,) taken out along the directions the
    match does not constrain (those eigen-directions left out by :func:`constrained_directions` that are
    mostly translation, yaw share at most ``max_yaw_share`` in the lever-scaled space: their translation
    parts), so that it measures the pose at the prior's place along them; unchanged when that part is
    shorter than ``min_shift`` (m; an alias lies a door frame or so away) or within ``min_sigmas`` of the
    prior's covariance ``prior_cov`` (3, 3), where the peak may well be where the robot is.

    Along a corridor the score repeats along the translation (aliases of doors or niches), while a few end
    points facing along it tilt the information's unconstrained direction into the yaw: a peak at an alias,
    fused in the constrained direction that mixes the yaw with that translation, would read as a heading
    error."""
    if not np.all(np.isfinite(information)) or not lever > 0:
        return pose
    _, vals, vecs = _lever_scaled_eigen(information, lever)
    free = vecs[:, vals < min_points / sigma_hit ** 2]
    along = free[:2, np.abs(free[2]) <= max_yaw_share]  # translation parts of those mostly translation (2, m)
    if along.shape[1] == 0:
        return pose
    coef = np.linalg.lstsq(along, np.asarray(pose[:2], dtype=np.float64) - prior[:2], rcond=None)[0]
    slide = along @ coef  # the translation from the prior along them (m, map frame)
    if np.hypot(*slide) < min_shift or slide @ np.linalg.solve(prior_cov[:2, :2], slide) <= min_sigmas ** 2:
        return pose
    out = np.array(pose, dtype=np.float64)
    out[:2] -= slide
    return out


def select_points(angles: np.ndarray, ranges: np.ndarray, mount: np.ndarray, config: MatcherConfig,
                  weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """End points usable for matching, in the base frame: returns (points (m, 2), weights (m,), beam index
    (m,)). Beams that are NaN, inf, outside [range_min, range_max] or with weight 0 are dropped; the rest
    are thinned to about one per ``voxel`` (m) of arc by beam index: a beam at range r is kept when its
    index is a multiple of the stride 2^round(log2(voxel / (r * angle increment))) (1 .. 64; the sets are
    nested, so the spacing is voxel / sqrt(2) .. voxel * sqrt(2) on a surface facing the laser); then evenly
    thinned to at most ``max_points``.

    Why by index and not "one beam per spatial voxel": which beam lands in a voxel depends on its range
    noise, so any rule that picks a beam by its rank within a voxel (the first, the last, even the middle
    of an even count) keeps end points whose noise has a particular sign, on the same side of each voxel,
    which is a small yaw bias per match that the map, built from the matched poses, accumulates (office,
    perfect odometry: 6.5 cm of lateral drift with the upper middle beam, 1.4 cm with the lower one, 5.9 cm
    with the first). The beam index carries no noise, and the stride is taken from the neighbouring beams'
    ranges, whose noise is independent of the beam's own."""
    ranges = np.asarray(ranges, dtype=np.float64)
    ok = np.isfinite(ranges) & (ranges >= config.range_min) & (ranges <= config.range_max)
    if weights is not None:
        ok &= np.isfinite(weights) & (weights > 0)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return np.zeros((0, 2)), np.zeros(0), idx
    angles = np.asarray(angles, dtype=np.float64)
    inc = _median(np.abs(np.diff(angles))) if angles.size > 1 else 1.0
    r = ranges[idx]
    # the stride comes from the neighbours' ranges, not the beam's own: otherwise whether a beam near a
    # stride boundary is kept would depend on the sign of its own range noise
    n = ranges.size
    lo, hi = ranges[np.maximum(idx - 1, 0)], ranges[np.minimum(idx + 1, n - 1)]
    lo = np.where(np.isfinite(lo) & (idx > 0), lo, np.nan)
    hi = np.where(np.isfinite(hi) & (idx < n - 1), hi, np.nan)
    both = np.isfinite(lo) & np.isfinite(hi)
    rs = np.where(both, 0.5 * (lo + hi), np.where(np.isfinite(lo), lo, np.where(np.isfinite(hi), hi, r)))
    # (np.minimum/np.maximum rather than np.clip, whose call costs more: the integers are the same)
    k = np.minimum(np.maximum(np.rint(np.log2(config.voxel / (np.maximum(rs, 1e-3) * max(inc, 1e-9)))), 0.0),
                   6.0).astype(np.int64)
    keep = (idx & ((1 << k) - 1)) == 0  # index multiple of the stride 2^k
    idx, r = idx[keep], r[keep]
    if idx.size > config.max_points:
        sel = np.linspace(0, idx.size - 1, config.max_points).astype(np.int64)
        idx, r = idx[sel], r[sel]
    a = mount[2] + angles[idx]
    pts = np.stack([mount[0] + r * np.cos(a), mount[1] + r * np.sin(a)], axis=1)
    w = np.ones(idx.size) if weights is None else np.asarray(weights, dtype=np.float64)[idx]
    return pts, w, idx


def _clamp(x: float, lo: float, hi: float) -> float:
    """float(np.clip(x, lo, hi)) of one number (lo <= hi; NaN stays NaN, as there), without np.clip's
    call overhead."""
    return float(min(max(x, lo), hi))


def _p90_and_median(r: np.ndarray) -> tuple[float, float]:
    """(np.percentile(r, 90), np.median(r)) of a 1-D array, from one sort: numpy's formulas (linear
    interpolation at (n - 1) * 0.9, as ``_lerp`` computes it; the mean of the middle two for an even n),
    so the same values to the last bit; with NaNs, numpy's own functions."""
    n = r.shape[0]
    srt = np.sort(r)
    if n == 0 or srt[-1] != srt[-1]:  # empty, or NaN (sorted last)
        return float(np.percentile(r, 90)), float(np.median(r))
    vi = (n - 1) * (90 / 100)
    if vi >= n - 1:
        p90 = float(srt[-1])
    else:
        i = int(np.floor(vi))
        a, b = float(srt[i]), float(srt[i + 1])
        g = vi - i
        p90 = b - (b - a) * (1 - g) if g >= 0.5 else a + (b - a) * g
    return p90, _sorted_median(srt)


def _sorted_median(srt: np.ndarray) -> float:
    """np.median of a sorted, non-empty 1-D array without NaN: the middle value, or the mean of the middle
    two ((a + b) / 2, as numpy's mean of two values)."""
    h = srt.shape[0] // 2
    return float(srt[h]) if srt.shape[0] % 2 else (float(srt[h - 1]) + float(srt[h])) / 2


def _median(x: np.ndarray) -> float:
    """np.median of a 1-D array, from one sort (numpy's own function when empty or with NaN)."""
    srt = np.sort(x)
    if srt.shape[0] == 0 or srt[-1] != srt[-1]:
        return float(np.median(x))
    return _sorted_median(srt)


# the 19 poses of _score_hessian in units of its steps h: the centre, +-1 along each axis, the 4 diagonal
# corners of each pair of axes (scaled by h > 0 they are the offsets it used to build per call, signed zeros
# included, so the poses are the same to the last bit)
_HESSIAN_PAIRS = ((0, 1), (0, 2), (1, 2))
_HESSIAN_STENCIL = np.array([np.zeros(3)] + [sg * np.eye(3)[k] for k in range(3) for sg in (1, -1)]
                            + [a * np.eye(3)[k] + b * np.eye(3)[m] for k, m in _HESSIAN_PAIRS
                               for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1))])


class CorrelativeMatcher:
    """Multi-resolution correlative matcher over a :class:`LikelihoodField`."""

    def __init__(self, config: MatcherConfig = MatcherConfig()) -> None:
        self.config = config

    def _scores(self, field_arr: np.ndarray, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray,
                xy0: np.ndarray, yaws: np.ndarray, tx: np.ndarray, ty: np.ndarray, margin: int,
                bilinear: bool = False) -> np.ndarray:
        """Scores (K, T) for yaws (K,) and integer cell translations (tx, ty) (T,) around xy0 (m, map frame;
        (2,), or (K, 2) for one per yaw: poses off the lattice).

        bilinear: interpolate the field between cell centres (smooth in sub-cell offsets; 4 lookups per
        point) instead of taking the cell the point falls in."""
        res = fld.resolution
        h, wd = fld.shape
        c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
        xy0 = np.asarray(xy0, dtype=np.float64).reshape(-1, 2)  # (1, 2) or one origin per yaw (K, 2)
        ox, oy = xy0[:, 0] - fld.origin[0], xy0[:, 1] - fld.origin[1]
        off = ty.astype(np.int64) * wd + tx.astype(np.int64)  # (T,)
        wf = w.astype(np.float32)
        px, py = np.ascontiguousarray(pts[:, 0], dtype=np.float64), np.ascontiguousarray(pts[:, 1], dtype=np.float64)
        if not bilinear:
            # points off the crop are clamped into its floor border; margin >= largest translation
            vals = cell_values(field_arr, px, py, c[:, 0], s[:, 0], ox, oy, res, off, margin, wd, h)  # (K, T, n)
            return vals @ wf
        if fld.vx is not None and field_arr is fld.fine:
            # interpolate the vector to the nearest wall point (affine in the position near a straight wall,
            # so bilinear interpolation is exact there) and take the likelihood of its length; interpolating
            # the likelihood itself pulls points towards cell centres (a bias that depends on where the
            # walls lie in their cells, and that the map accumulates)
            p = fld.params
            d2 = scaled_squared_distances(fld.vx, fld.vy, px, py, c[:, 0], s[:, 0], ox, oy, res, off, margin, wd, h,
                                          np.float32(-0.5 / p.sigma_hit ** 2))
            np.exp(d2, out=d2)  # log(exp(d2) + p_floor), in place (the same ufuncs, no temporaries)
            d2 += np.float32(p.p_floor)
            np.log(d2, out=d2)
            return d2 @ wf
        fx = (c * pts[:, 0] - s * pts[:, 1] + (xy0[:, :1] - fld.origin[0])) / res
        fy = (s * pts[:, 0] + c * pts[:, 1] + (xy0[:, 1:] - fld.origin[1])) / res
        gx, gy = fx - 0.5, fy - 0.5  # cell centres at integer coordinates
        x0, y0 = np.floor(gx), np.floor(gy)
        ax, ay = (gx - x0).astype(np.float32), (gy - y0).astype(np.float32)
        ix = np.clip(x0.astype(np.int64), margin, wd - 2 - margin)
        iy = np.clip(y0.astype(np.int64), margin, h - 2 - margin)
        base = (iy * wd + ix)[:, None, :] + off[None, :, None]  # (K, T, n)
        corners = ((0, (1 - ax) * (1 - ay)), (1, ax * (1 - ay)), (wd, (1 - ax) * ay), (wd + 1, ax * ay))
        out = np.zeros((len(yaws), len(off)), dtype=np.float32)
        for dflat, coef in corners:
            vals = field_arr[base + dflat]  # (K, T, n)
            out += np.matmul(vals, (coef * wf)[:, :, None])[..., 0]
        return out

    def match(self, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray, prior_pose: np.ndarray,
              prior_cov: np.ndarray) -> MatchResult | None:
        """Match base-frame end points ``pts`` (n, 2) with weights ``w`` (n,) around ``prior_pose`` (map
        frame). Returns None when the field is empty, there are too few points or the match is poor."""
        cfg = self.config
        if not fld.ready or pts.shape[0] < cfg.min_points or w.sum() <= 0:
            return None
        res = fld.resolution
        f = fld.params.coarse_factor
        prior_pose = np.asarray(prior_pose, dtype=np.float64)
        sig_xy = float(np.sqrt(max(np.linalg.eigvalsh(prior_cov[:2, :2]).max(), 0.0)))
        sig_yaw = float(np.sqrt(max(prior_cov[2, 2], 0.0)))
        win_xy = _clamp(cfg.window_sigmas * sig_xy, cfg.xy_window_min, cfg.xy_window_max)
        win_yaw = _clamp(cfg.window_sigmas * sig_yaw, cfg.yaw_window_min, cfg.yaw_window_max)
        r90, r_median = _p90_and_median(np.hypot(pts[:, 0], pts[:, 1]))
        step = _clamp(res / max(r90, 1e-3), cfg.yaw_step_min, cfg.yaw_step_max)

        # coarse: block translations t (block covers [t, t+f) cells), yaw step f * step
        nb = int(np.ceil(win_xy / (res * f)))
        hf, hy = max(cfg.fine_half_cells, f), max(cfg.fine_half_yaw, f // 2 + 1)
        margin = nb * f + 2 * hf + f  # largest translation (cells) a lookup can get
        if 2 * margin > fld.params.pad:  # keep lookups of off-crop points inside the floor border
            margin = fld.params.pad // 2
            nb = max(1, (margin - 2 * hf - f) // f)
        tb = np.arange(-nb, nb) * f
        tx_c, ty_c = np.meshgrid(tb, tb, indexing="xy")
        tx_c, ty_c = tx_c.ravel(), ty_c.ravel()
        ky = int(np.ceil(win_yaw / (f * step)))
        yaw_c = prior_pose[2] + np.arange(-ky, ky + 1) * f * step
        xy0 = prior_pose[:2]
        sc = self._scores(fld.coarse, fld, pts, w, xy0, yaw_c, tx_c, ty_c, margin)
        n_poses = sc.size
        order = np.argsort(sc, axis=None)[::-1]

        # fine: first the window centred on the prior (so that a flat direction, e.g. along a corridor,
        # gives back the prior's value and no bias), then the best coarse candidates while their upper
        # bound beats the best fine score; another window replaces the prior's only if clearly better.
        dx = np.arange(-hf, hf + 1)
        ftx, fty = np.meshgrid(dx, dx, indexing="xy")
        ftx, fty = ftx.ravel(), fty.ravel()
        dk = np.arange(-hy, hy + 1)
        beta = min(1.0, cfg.independent_points / float(w.sum()))
        starts = [(0, 0, prior_pose[2])]
        for flat in order[: cfg.max_refine]:
            k, t = np.unravel_index(flat, sc.shape)
            starts.append((tx_c[t] + f // 2, ty_c[t] + f // 2, yaw_c[k], sc[k, t]))
        best = None
        for n_start, start in enumerate(starts):
            cx, cy, cyaw = start[0], start[1], start[2]
            if best is not None and start[3] <= best[0]:  # its upper bound cannot beat the best
                break
            for it in range(4):  # re-centre when the peak sits on the window's edge
                yaws = cyaw + dk * step
                sf = self._scores(fld.fine, fld, pts, w, xy0, yaws, cx + ftx, cy + fty, margin, cfg.bilinear)
                n_poses += sf.size
                kk, tt = np.unravel_index(np.argmax(sf), sf.shape)
                edge = (abs(dk[kk]) == hy) or (abs(ftx[tt]) == hf) or (abs(fty[tt]) == hf)
                cand = (float(sf[kk, tt]), sf, cx, cy, cyaw, yaws, edge, kk, tt)
                if best is None or ((it > 0 and n_start == 0 or best[6]) and cand[0] > best[0]) or \
                        cand[0] - best[0] > cfg.switch_margin:
                    best = cand
                if not edge or abs(cx + ftx[tt]) + hf > margin or abs(cy + fty[tt]) + hf > margin:
                    break
                cx, cy, cyaw = cx + ftx[tt], cy + fty[tt], yaws[kk]
        smax, sf, cx, cy, cyaw, yaws, edge, kk, tt = best
        quality = float(np.exp(smax / w.sum()) / (1.0 + fld.params.p_floor))
        if quality < cfg.min_quality:
            return None

        pi = np.exp(beta * (sf - smax)).astype(np.float64)
        pi /= pi.sum()
        px = xy0[0] + (cx + ftx) * res  # (T,)
        py = xy0[1] + (cy + fty) * res
        dyaw = yaws - cyaw  # (K,)
        pk, pt = pi.sum(axis=1), pi.sum(axis=0)
        mx, my, mk = pt @ px, pt @ py, pk @ dyaw
        ex, ey = px - mx, py - my
        ek = dyaw - mk
        cov = np.empty((3, 3))
        cov[0, 0] = pt @ (ex * ex)
        cov[1, 1] = pt @ (ey * ey)
        cov[0, 1] = cov[1, 0] = pt @ (ex * ey)
        cov[2, 2] = pk @ (ek * ek)
        cov[0, 2] = cov[2, 0] = ek @ pi @ ex
        cov[1, 2] = cov[2, 1] = ek @ pi @ ey
        # sub-lattice peak: a parabola through the peak and its two neighbours on each axis (the scores are
        # smooth thanks to the bilinear field). The mean of pi would snap to the lattice when pi is narrow
        # and lean towards the window's centre when pi is truncated, so the vertex is the measurement on
        # every axis where the scores curve down; the mean only on flat axes.
        n1 = 2 * hf + 1
        cube = sf.reshape(len(yaws), n1, n1)  # (yaw, y, x)
        k0, j0, i0 = int(kk), int(tt) // n1, int(tt) % n1
        sub = np.zeros(3)  # (x, y, yaw) offsets in lattice steps
        curved = np.zeros(3, dtype=bool)
        for axis, (idx, size) in enumerate(((i0, n1), (j0, n1), (k0, len(yaws)))):
            if 0 < idx < size - 1:
                sl = [k0, j0, i0]
                vals = []
                for d in (-1, 0, 1):
                    sl2 = list(sl)
                    sl2[2 - axis] = idx + d
                    vals.append(float(cube[tuple(sl2)]))
                den = vals[0] - 2 * vals[1] + vals[2]
                if den < 0:
                    curved[axis] = True
                    sub[axis] = _clamp(0.5 * (vals[0] - vals[2]) / den, -0.5, 0.5)
        peak = np.array([px[tt] + sub[0] * res, py[tt] + sub[1] * res, yaws[kk] + sub[2] * step])
        mean = np.array([mx, my, cyaw + mk])
        pose = np.where(curved, peak, mean)
        within, n_within = self._within_cell_covariance(fld, pts, w, np.array([px[tt], py[tt], yaws[kk]]), step,
                                                        beta, margin)
        cov += within
        n_poses += n_within
        info = self.information(fld, pts, w, pose)
        return MatchResult(pose=pose, covariance=cov, peak_pose=peak, quality=quality,
                           n_points=int(pts.shape[0]), n_poses=int(n_poses), edge=bool(edge),
                           lever=r_median, information=info)

    def information(self, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Information (3x3, inverse covariance over x, y, yaw; untempered) of the end points at ``pose``
        about the pose, from the geometry of the walls they lie on (Gauss-Newton): each end point's residual
        is its vector v(q) to the nearest wall point, whose Jacobian J = dv/dq is -n n^T on a straight wall
        of normal n (the point may slide along the wall) and -I at an isolated wall point. A point within
        sigma_hit of the wall adds w r A^T A / sigma_hit^2 with A = J [I, perp(R p)] and r its inlier weight
        (the Gaussian's share of the likelihood). A straight wall gives nothing along itself, however its
        end points scatter. (The score's own curvature over a lattice step is not a test: end points moving
        in and out of the ragged edge of the map, where grazing beams cleared cells, make a featureless
        corridor look constrained.)"""
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rp = np.stack([c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]], axis=1)
        q = pose[:2] + rp
        eps = 0.25 * fld.resolution
        offs = np.array([[0.0, 0.0], [eps, 0.0], [-eps, 0.0], [0.0, eps], [0.0, -eps]])
        vs = fld.wall_vectors((q[None, :, :] + offs[:, None, :]).reshape(-1, 2)).reshape(5, -1, 2)  # one gather
        v = vs[0]
        jx, jy = (vs[1] - vs[2]) / (2 * eps), (vs[3] - vs[4]) / (2 * eps)  # dv/dx, dv/dy (n, 2)
        p = fld.params
        d = np.hypot(v[:, 0], v[:, 1])
        ok = np.isfinite(d) & (d < p.sigma_hit) & np.all(np.isfinite(jx) & np.isfinite(jy), axis=1)
        if not ok.any():
            return np.zeros((3, 3))
        jac = np.stack([jx[ok], jy[ok]], axis=2)  # (m, 2, 2): [component, d/dx or d/dy]
        lever = np.stack([-rp[ok, 1], rp[ok, 0]], axis=1)  # d(R p)/d(yaw)
        a = np.concatenate([jac, np.einsum("mij,mj->mi", jac, lever)[:, :, None]], axis=2)  # (m, 2, 3)
        g = np.exp(-0.5 * (d[ok] / p.sigma_hit) ** 2)
        r = w[ok] * g / (g + p.p_floor)
        return np.einsum("m,mki,mkj->ij", r, a, a) / p.sigma_hit ** 2

    def _within_cell_covariance(self, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray, center: np.ndarray,
                                step: float, beta: float, margin: int) -> tuple[np.ndarray, int]:
        """(Covariance (3x3), poses scored) of pi inside the cell of the best lattice pose ``center`` (a cell
        is one lattice step along x, y and yaw). The lattice moments see each cell's mass at its centre only;
        by the law of total variance the rest is the spread inside the cells, taken as that of the peak's.

        It is the Gaussian of the peak's curvature, (beta H)^-1 with H the Hessian of -score by central
        differences, taken twice: with steps of a fifth of the cell, then of the standard deviations this
        gave (the score is quadratic near the peak, not across the whole cell, where end points leave the
        Gaussian part of the field). On an axis where that is wider than the cell, the lattice moments
        already hold the spread, and the axis is scaled down to that of a uniform distribution over the
        cell (step^2 / 12); where the score does not curve down (flat, or not a peak at this scale) the
        whole cell is uniform (docs/pose.md: why not a sampled moment)."""
        size = np.array([fld.resolution, fld.resolution, step])
        uniform = size ** 2 / 12.0
        h = size / 5
        for n_scored in (19, 38):
            hess = self._score_hessian(fld, pts, w, center, h, margin)
            if np.linalg.eigvalsh(hess)[-1] >= 0:
                return np.diag(uniform), n_scored
            cov = np.linalg.inv(-beta * hess)
            h = np.clip(np.sqrt(np.diag(cov)), size / 100, size / 5)
        scale = np.minimum(1.0, np.sqrt(uniform / np.diag(cov)))
        return cov * np.outer(scale, scale), n_scored

    def _pose_scores(self, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray, poses: np.ndarray,
                     margin: int) -> np.ndarray:
        """Scores (P,) of arbitrary poses (P, 3) (map frame) on the fine field."""
        zero = np.zeros(1, dtype=np.int64)
        return self._scores(fld.fine, fld, pts, w, poses[:, :2], poses[:, 2], zero, zero, margin,
                            self.config.bilinear)[:, 0].astype(np.float64)

    def _score_hessian(self, fld: LikelihoodField, pts: np.ndarray, w: np.ndarray, pose: np.ndarray,
                       h: np.ndarray, margin: int) -> np.ndarray:
        """Hessian (3x3) of the score at ``pose`` by central differences with steps ``h`` (3,) (19 poses)."""
        sc = self._pose_scores(fld, pts, w, pose + _HESSIAN_STENCIL * h, margin)
        hess = np.empty((3, 3))
        for k in range(3):
            hess[k, k] = (sc[1 + 2 * k] - 2 * sc[0] + sc[2 + 2 * k]) / h[k] ** 2
        for q, (k, m) in enumerate(_HESSIAN_PAIRS):
            pp, pm, mp, mm = sc[7 + 4 * q: 11 + 4 * q]
            hess[k, m] = hess[m, k] = (pp - pm - mp + mm) / (4 * h[k] * h[m])
        return hess


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the compiled lookups now, with the argument types the
    matcher passes, rather than at the first key scan (a live run would miss scans meanwhile)."""
    fld = LikelihoodField()
    fld.shape = (8, 8)
    fld.fine = fld.coarse = fld.vx = fld.vy = np.zeros(64, dtype=np.float32)
    m, pts, w, zero = CorrelativeMatcher(), np.zeros((1, 2)), np.ones(1), np.zeros(1, dtype=np.int64)
    m._scores(fld.coarse, fld, pts, w, np.zeros(2), np.zeros(1), zero, zero, 1)
    m._scores(fld.fine, fld, pts, w, np.zeros(2), np.zeros(1), zero, zero, 1, bilinear=True)
    warm_up_estimator()  # and the estimator's per-beam loops and the field's maximum filter, which the first
    warm_up_field()  # scan and the first field rebuild would load
    warm_up_filter()  # (and the filter's small-matrix steps)
