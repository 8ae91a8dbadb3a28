"""Likelihood field for scan matching, derived from the occupancy grid (map frame).

Each cell holds the log-likelihood of a beam end point falling in it:
``log(exp(-d^2 / (2 sigma_hit^2)) + p_floor)`` with d the distance (m) to the nearest occupied cell; the
floor stands for everything the map does not explain (people, glass seen for the first time, unknown
space). A second array holds, per cell, the maximum over the ``f x f`` block starting at that cell: looking
a point up there gives an upper bound of the fine score over a coarse translation step (multi-resolution
search). With ``FieldParams.vectors`` two more arrays hold, per cell near a wall, the vector (m) from the
cell centre to the wall point (along the wall's normal where the wall is straight): the matcher's fine stage
interpolates that vector, not the likelihood (see :meth:`LikelihoodField.log_likelihood`). The field covers
a square crop around the robot and is rebuilt from the grid when asked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from glassmap.grid import OccupancyGrid


FAR = 10.0  # m: the vector stored where no wall is within the cut-off (the likelihood there is the floor)
# Per-cell end-point layers with faces (:func:`accumulate_hits`; offsets in metres from the cell's corner): the
# sums over all end points in the cell (x offset, y offset, count, unit normal x, unit normal y), then the same
# five sums over those of the cell's first face; the second face is the difference.
FACE_LAYERS = ("sx", "sy", "n", "nx", "ny", "a_sx", "a_sy", "a_n", "a_nx", "a_ny")


def end_point_normals(angles: np.ndarray, ranges: np.ndarray, valid: np.ndarray, support: float = 0.1,
                      max_beams: int = 10, gap: float = 0.2) -> np.ndarray:
    """Unit normals (n, 2) (laser frame, pointing back towards the sensor) of the surface at each beam's end
    point, from a line fitted to the end points of the beams i - k..i or i..i + k (k beams spanning about
    ``support`` m at that range, 2..max_beams), whichever side is straighter: a point at a corner gets the
    normal of one of its faces, not a blend of both. A side stops before an invalid beam or a gap above
    ``gap`` m between consecutive end points (at least 3 points); without a usable side the normal points
    back along the beam.
    angles (rad), ranges (m), valid (bool) of shape (n,)."""
    n = ranges.size
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    if n < 3:
        return -u
    r = np.where(valid, ranges, 0.0)
    x, y = r * u[:, 0], r * u[:, 1]
    dth = max(float(np.median(np.abs(np.diff(angles)))), 1e-6)
    k = np.clip(np.ceil(support / np.maximum(r * dth, 1e-6)), 2, max_beams).astype(np.int64)
    gaps = np.concatenate([[False], np.hypot(np.diff(x), np.diff(y)) > gap])
    # runs of valid beams without a gap: a window stays inside its beam's run
    i = np.arange(n)
    cut = gaps | ~valid | np.concatenate([[False], ~valid[:-1]])
    start = np.maximum.accumulate(np.where(cut, i, 0))
    end = (n - 1 - np.maximum.accumulate(np.where(np.concatenate([cut[1:], [True]]), n - 1 - i, 0)[::-1])[::-1])

    def csum(a):
        return np.concatenate([[0.0], np.cumsum(a, dtype=np.float64)])

    cx, cy, cxx, cxy, cyy = (csum(a) for a in (x, y, x * x, x * y, y * y))
    fits = []
    for lo, hi in ((np.maximum(i - k, start), i), (i, np.minimum(i + k, end))):
        ok = valid & (hi - lo >= 2)
        m = (hi - lo + 1).astype(np.float64)
        mx, my = (cx[hi + 1] - cx[lo]) / m, (cy[hi + 1] - cy[lo]) / m
        sxx = (cxx[hi + 1] - cxx[lo]) / m - mx * mx
        syy = (cyy[hi + 1] - cyy[lo]) / m - my * my
        sxy = (cxy[hi + 1] - cxy[lo]) / m - mx * my
        theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the line
        lmin = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy * sxy)
        fits.append((ok, lmin, np.stack([-np.sin(theta), np.cos(theta)], axis=1)))
    (ok_l, e_l, n_l), (ok_r, e_r, n_r) = fits
    left = ok_l & (~ok_r | (e_l <= e_r))
    nrm = np.where(left[:, None], n_l, n_r)
    nrm = np.where((ok_l | ok_r)[:, None], nrm, -u)
    return np.where((np.sum(nrm * u, axis=1) > 0)[:, None], -nrm, nrm)


def accumulate_hits(layers: tuple[np.ndarray, ...], flat: np.ndarray, off: np.ndarray, normals: np.ndarray,
                    face_cos: float = 0.5) -> None:
    """Add end points to the per-cell :data:`FACE_LAYERS` (flat float arrays, changed in place): flat (n,) cell
    indices, off (n, 2) offsets (m) from the cell's corner, normals (n, 2) unit normals (map frame, e.g.
    :func:`end_point_normals` rotated). A point joins the cell's first face when its normal agrees better with
    that face's mean normal than with the second's (or, while the cell has one face, when their cosine is at
    least ``face_cos``); a cell without points takes its first face from the first of them here. So the two
    faces of a convex corner, or the two sides of a thin wall, stay apart within a cell."""
    def unit(ax, ay):
        m = np.hypot(ax, ay)
        m = np.where(m > 0, m, 1.0)
        return np.stack([ax / m, ay / m], axis=1)

    n, nx, ny, an, anx, any_ = (layers[j][flat].astype(np.float64) for j in (2, 3, 4, 7, 8, 9))
    _, first, inv = np.unique(flat, return_index=True, return_inverse=True)
    ref = np.where((an > 0)[:, None], unit(anx, any_), normals[first][inv.reshape(-1)])
    ca = np.sum(normals * ref, axis=1)
    cb = np.sum(normals * unit(nx - anx, ny - any_), axis=1)
    to_a = np.where(n - an > 0, ca >= cb, ca >= face_cos)
    vals = (off[:, 0], off[:, 1], np.ones(flat.size), normals[:, 0], normals[:, 1])
    for j, v in enumerate(vals):
        np.add.at(layers[j], flat, v.astype(layers[j].dtype))
        np.add.at(layers[5 + j], flat[to_a], v[to_a].astype(layers[j].dtype))


@dataclass(frozen=True)
class FieldParams:
    """sigma_hit (m): end-point spread around a wall; p_floor: uniform floor (relative to the peak 1);
    occupied_log_odds: cells above it count as walls; half_size (m): half-width of the crop around the
    robot; pad (cells): border of floor cells so that lookups near the edge stay in the array;
    coarse_factor: cells per coarse step of the multi-resolution search; pool (cells): the wall position of
    an occupied cell is the mean of the end points that fell in the (2 pool + 1)^2 cells around it (0: only
    its own; see :meth:`LikelihoodField.compute`); vectors: also store, per cell, the vector (m) from the
    cell centre to the nearest wall point, for :meth:`LikelihoodField.log_likelihood` and the matcher's
    fine stage (bilinear interpolation of the vector is exact near a wall, that of the likelihood is not);
    line_normals: where the neighbourhood's end points form a straight wall (smaller / larger scatter
    eigenvalue below line_ratio), measure the distance along the wall's normal only (see
    :meth:`LikelihoodField._pooled`); sigma_hit (m): standard deviation of the Gaussian of the distance to the
    nearest wall point; face_cos: with face layers (see :data:`FACE_LAYERS`), end points of two cells belong
    to the same face when the cosine between their faces' mean normals is at least this."""

    sigma_hit: float = 0.03
    p_floor: float = 0.05
    occupied_log_odds: float = 0.6
    half_size: float = 14.0
    pad: int = 64
    coarse_factor: int = 4
    pool: int = 1
    vectors: bool = True
    line_normals: bool = True
    line_ratio: float = 0.25
    face_cos: float = 0.8


@dataclass(frozen=True)
class FieldInputs:
    """What a field rebuild reads from the grid: the occupied mask of the crop (None if the crop is empty),
    the crop of the end-point layers, the crop centre (m), the grid generation and resolution, and the
    map-frame corner of the crop (m)."""

    occupied: np.ndarray | None
    points: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    center: np.ndarray
    generation: int
    resolution: float
    crop_origin: np.ndarray


@dataclass(frozen=True)
class FieldArrays:
    """A computed field (flat fine and coarse arrays of ``shape``) and the snapshot it came from."""

    inputs: FieldInputs
    fine: np.ndarray | None
    coarse: np.ndarray | None
    shape: tuple[int, int]
    n_occupied: int
    vx: np.ndarray | None = None
    vy: np.ndarray | None = None


class LikelihoodField:
    """Fine and coarse (block-max) log-likelihood arrays over a crop of the occupancy grid.

    ``origin`` is the map-frame (x, y) of the corner of cell (0, 0) of the arrays, ``resolution`` the grid's.
    Arrays are indexed ``[iy, ix]`` and stored flat for fast gathers.
    """

    def __init__(self, params: FieldParams = FieldParams()) -> None:
        self.params = params
        self.fine: np.ndarray | None = None
        self.coarse: np.ndarray | None = None
        self.vx: np.ndarray | None = None  # flat, vector (m) from each cell centre to the nearest wall point
        self.vy: np.ndarray | None = None
        self.origin = np.zeros(2)
        self.resolution = 0.05
        self.shape = (0, 0)
        self.n_occupied = 0
        self.center = np.zeros(2)
        self.generation = -1

    @property
    def ready(self) -> bool:
        return self.fine is not None and self.n_occupied > 0

    @property
    def floor(self) -> float:
        return float(np.log(self.params.p_floor))

    def rebuild(self, occupancy: OccupancyGrid, center_xy: np.ndarray,
                points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
        """Recompute the field from ``occupancy`` on the crop centred on ``center_xy`` (map frame, m).

        points: optional full-grid layers (sum of x offsets, sum of y offsets, count) of the end points that
        fell in each cell, offsets in metres from the cell's corner. Distances are then measured to the mean
        end point of the nearest occupied cell instead of its centre: a wall that does not lie on a cell
        centre is no longer moved by up to half a cell (which would bias matching by about a centimetre
        and make the map creep as new walls come into view).

        Equivalent to ``install(compute(snapshot(...)))``; the estimator runs :meth:`compute` in a worker
        thread (it touches no shared state) and installs the result at the next key scan."""
        self.install(self.compute(self.snapshot(occupancy, center_xy, points)))

    def snapshot(self, occupancy: OccupancyGrid, center_xy: np.ndarray,
                 points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> FieldInputs:
        """Copy what :meth:`compute` needs from the grid (the crop around ``center_xy``): cheap, and the grid
        may change afterwards."""
        p = self.params
        g = occupancy.grid
        res = g.resolution
        h, w = g.shape
        half = int(np.ceil(p.half_size / res))
        cx, cy = g.world_to_cell(np.asarray(center_xy, dtype=np.float64))
        x0, x1 = max(cx - half, 0), min(cx + half + 1, w)
        y0, y1 = max(cy - half, 0), min(cy + half + 1, h)
        empty = x1 <= x0 or y1 <= y0
        occ = None if empty else occupancy.log_odds[y0:y1, x0:x1] > p.occupied_log_odds
        pts = None if (empty or points is None) else tuple(a[y0:y1, x0:x1].copy() for a in points)
        return FieldInputs(occ, pts, np.asarray(center_xy, dtype=np.float64).copy(), g.generation, res,
                           g.origin + np.array([x0, y0]) * res)

    def compute(self, inputs: FieldInputs) -> FieldArrays:
        """The field arrays of a snapshot (pure: no shared state, safe in a worker thread)."""
        p = self.params
        res = inputs.resolution
        occ = inputs.occupied
        if occ is None:
            return FieldArrays(inputs, None, None, (0, 0), 0)
        n_occupied = int(occ.sum())
        pad = p.pad
        floor = np.float32(np.log(p.p_floor))
        field = np.full((occ.shape[0] + 2 * pad, occ.shape[1] + 2 * pad), floor, dtype=np.float32)
        vx = vy = None
        if p.vectors:  # "far": a vector long enough that the Gaussian is below the floor's resolution
            vx = np.full(field.shape, np.float32(FAR), dtype=np.float32)
            vy = np.zeros(field.shape, dtype=np.float32)
        if n_occupied:
            # beyond cut (m) the Gaussian is negligible against the floor (< 1e-4 in log), so only the cells
            # that close to a wall are computed; the rest keep the floor
            cut = p.sigma_hit * float(np.sqrt(-2.0 * np.log(1e-4 * p.p_floor))) + res
            inner = field[pad:-pad, pad:-pad]
            ny, nx = ndimage.distance_transform_edt(~occ, return_distances=False, return_indices=True)
            ddy = ny - np.arange(occ.shape[0], dtype=ny.dtype)[:, None]  # cells to the nearest occupied cell
            ddx = nx - np.arange(occ.shape[1], dtype=nx.dtype)[None, :]
            cut_c = int(np.ceil(cut / res))
            near = np.nonzero(ddx * ddx + ddy * ddy <= cut_c * cut_c)
            ny, nx, ddy, ddx = ny[near], nx[near], ddy[near], ddx[near]
            points, pool = inputs.points, p.pool
            if points is None:  # no end-point layers: one point at the centre of each occupied cell (cell
                cnt0 = occ.astype(np.float64)  # centres carry no measurement bias: nothing to pool)
                points, pool = (0.5 * res * cnt0, 0.5 * res * cnt0, cnt0), 0
            # the wall point and normal are needed only at the occupied cells some near cell is closest to
            u, inv = np.unique(ny.astype(np.int64) * occ.shape[1] + nx, return_inverse=True)
            uy, ux = np.divmod(u, occ.shape[1])
            if len(points) == len(FACE_LAYERS) and p.line_normals:
                ex, ey = self._face_vectors(points, res, uy, ux, inv.reshape(-1), ddx, ddy)
            else:
                ex, ey = self._wall_vectors(points, res, pool, uy, ux, inv.reshape(-1), ddx, ddy)
            d = np.hypot(ex, ey)
            inner[near] = np.log(np.exp(-0.5 * (d / p.sigma_hit) ** 2) + p.p_floor).astype(np.float32)
            if vx is not None:
                vx[pad:-pad, pad:-pad][near] = ex
                vy[pad:-pad, pad:-pad][near] = ey
        f = p.coarse_factor
        coarse = ndimage.maximum_filter(field, size=f, origin=-(f // 2), mode="nearest")
        return FieldArrays(inputs, field.ravel(), coarse.ravel(), field.shape, n_occupied,
                           None if vx is None else vx.ravel(), None if vy is None else vy.ravel())

    def _wall_vectors(self, points: tuple[np.ndarray, ...], res: float, pool: int, uy: np.ndarray, ux: np.ndarray,
                      inv: np.ndarray, ddx: np.ndarray, ddy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectors (m) from the near cells' centres to the wall of their nearest occupied cell (uy, ux)[inv],
        ddx / ddy cells away, from (sum x, sum y, count) layers without faces (see :meth:`_pooled`)."""
        sx, sy, c, nrm = self._pooled(points[:3], res, pool, uy, ux)
        has = c > 0
        cs = np.where(has, c, 1)
        mx = np.where(has, sx / cs, 0.5 * res)[inv]  # mean offset in the cell (m)
        my = np.where(has, sy / cs, 0.5 * res)[inv]
        ex, ey = (ddx - 0.5) * res + mx, (ddy - 0.5) * res + my  # cell centre -> wall point (m)
        if nrm is not None:  # straight wall there: distance along its normal only
            nx_, ny_ = nrm[0][inv], nrm[1][inv]
            line = (has & nrm[2])[inv]
            dot = ex * nx_ + ey * ny_
            ex, ey = np.where(line, dot * nx_, ex), np.where(line, dot * ny_, ey)
        return ex, ey

    def _face_vectors(self, points: tuple[np.ndarray, ...], res: float, uy: np.ndarray, ux: np.ndarray,
                      inv: np.ndarray, ddx: np.ndarray, ddy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`_wall_vectors` from :data:`FACE_LAYERS`, one wall per face: each face of the occupied cell
        (uy, ux) is built from the end points of the faces around it whose mean normal agrees with its own
        (cosine >= ``face_cos``): its wall point the mean of those in the 3 x 3 cells, its line the scatter of
        those in the 5 x 5 cells. A near cell's vector goes to the nearest face of its occupied cell that it
        lies in front of (or, behind all, the one it is least deep behind: the solid of a convex corner is
        the intersection of its faces' half-planes). Near a convex corner the end points of the other face no longer chamfer the wall into the
        solid (see docs/pose.md, "A likelihood field exact at convex corners")."""
        prm = self.params
        h, w = points[2].shape
        d = np.arange(-2, 3)
        dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
        yy, xx = uy[:, None] + dy[None, :], ux[:, None] + dx[None, :]  # (U, 25) neighbours
        inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        yy, xx = np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)

        def read(j):
            return np.where(inside, points[j][yy, xx], 0).astype(np.float64)

        tot, fa = [read(j) for j in range(5)], [read(5 + j) for j in range(5)]
        # (U, 2 faces, 25): count, offset sums from the requested cell's corner (m), normal sums
        c = np.stack([fa[2], tot[2] - fa[2]], axis=1)
        ax = np.stack([fa[0], tot[0] - fa[0]], axis=1) + c * (dx * res)
        ay = np.stack([fa[1], tot[1] - fa[1]], axis=1) + c * (dy * res)
        gx, gy = np.stack([fa[3], tot[3] - fa[3]], axis=1), np.stack([fa[4], tot[4] - fa[4]], axis=1)
        gn = np.hypot(gx, gy)
        gn = np.where(gn > 0, gn, 1.0)
        gx, gy = gx / gn, gy / gn
        centre = dy.size // 2
        m3 = (np.abs(dy) <= 1) & (np.abs(dx) <= 1)
        cs = np.where(c > 0, c, 1.0)
        best_key = np.full(inv.size, np.inf)
        out_x = (ddx * res).astype(np.float64)  # fallback: the occupied cell's centre
        out_y = (ddy * res).astype(np.float64)
        for f in range(2):
            own = c[:, f, centre] > 0
            agree = (c > 0) & (gx * gx[:, f, centre, None, None] + gy * gy[:, f, centre, None, None]
                               >= prm.face_cos)
            agree[:, f, centre] = own
            a3 = agree & m3
            n3 = np.sum(c * a3, axis=(1, 2))
            n3s = np.where(n3 > 0, n3, 1.0)
            px, py = np.sum(ax * a3, axis=(1, 2)) / n3s, np.sum(ay * a3, axis=(1, 2)) / n3s
            n5 = np.sum(c * agree, axis=(1, 2))
            ns = np.where(n5 > 0, n5, 1.0)
            mx, my = np.sum(ax * agree, axis=(1, 2)) / ns, np.sum(ay * agree, axis=(1, 2)) / ns
            cxx = np.sum(ax * ax / cs * agree, axis=(1, 2)) / ns - mx * mx
            cyy = np.sum(ay * ay / cs * agree, axis=(1, 2)) / ns - my * my
            cxy = np.sum(ax * ay / cs * agree, axis=(1, 2)) / ns - mx * my
            half_tr, diff = 0.5 * (cxx + cyy), 0.5 * (cxx - cyy)
            rad = np.sqrt(diff * diff + cxy * cxy)
            lmax, lmin = half_tr + rad, half_tr - rad
            theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # direction of the wall
            line = (n5 >= 3) & (lmax > (0.5 * res) ** 2) & (lmin < prm.line_ratio * lmax)
            tx, ty = np.cos(theta), np.sin(theta)
            # the face's outward normal (towards where its end points were seen from): the scans' mean normal,
            # and the line's normal turned to agree with it
            ox, oy = np.sum(gx * gn * agree, axis=(1, 2)), np.sum(gy * gn * agree, axis=(1, 2))
            flip = np.where(-ty * ox + tx * oy < 0, -1.0, 1.0)
            nx_, ny_ = (-ty * flip)[inv], (tx * flip)[inv]
            # per near cell: vector to the face's wall point, along the normal where the face is a line (a line
            # is not cut where its end points end: an end may just be where the wall was not seen yet)
            ex, ey = (ddx - 0.5) * res + px[inv], (ddy - 0.5) * res + py[inv]
            dot = ex * nx_ + ey * ny_
            ln = line[inv]
            vx, vy = np.where(ln, dot * nx_, ex), np.where(ln, dot * ny_, ey)
            front = np.where(ln, -dot, np.where(ex * ox[inv] + ey * oy[inv] <= 0, 1.0, -1.0) * np.hypot(ex, ey))
            # the nearest face the cell lies in front of; behind all of them (inside the solid of a convex
            # corner), the one it is least deep behind
            key = np.where(front >= 0, front, 1e3 - front)
            take = own[inv] & (key < best_key)
            best_key = np.where(take, key, best_key)
            out_x, out_y = np.where(take, vx, out_x), np.where(take, vy, out_y)
        return out_x, out_y

    def _pooled(self, points: tuple[np.ndarray, np.ndarray, np.ndarray], res: float, k: int, cy: np.ndarray,
                cx: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """At the cells (cy, cx): (sum of x offsets, sum of y offsets, count) of the end points in the
        (2 k + 1)^2 cells around each (k = pool), offsets from that cell's corner (m), and the local wall
        normal (unit x, unit y, is-a-line) or None when ``line_normals`` is off. Only the requested cells and
        their neighbours are read.

        Why pool: the occupancy update clears the cells in front of a surface (beams pass through them) but
        never the cells behind it, so end points placed a little too far (range noise, pose error) leave an
        occupied cell behind the surface while those placed too short are erased. With per-cell means the
        walls of the likelihood field then lean away from where they were seen from, the match pushes the
        robot towards what it looks at (forward while driving) and the map, built from the matched poses,
        inherits it: a drift along the direction of travel (office: +0.25 % of the distance with perfect
        odometry). Pooling all end points of the neighbourhood, including the ones in cells that were
        cleared, puts the wall back at the mean of everything that was measured there.

        Normals: the count-weighted scatter of the cell means in the 5 x 5 neighbourhood (long enough for a
        wall two cells thick to look like a line); where it is elongated (smaller eigenvalue below
        ``line_ratio`` times the larger) the cells are a straight wall and the field measures the distance
        along its normal. Measuring to the mean point of the nearest cell would add a saw-tooth along the
        wall (up to half a cell between two cells' points): a false along-wall constraint in corridors and a
        bias wherever the points sit unevenly in their cells."""
        sx, sy, cnt = (np.asarray(a) for a in points)
        h, w = cnt.shape
        if k <= 0 and not self.params.line_normals:
            return (sx[cy, cx].astype(np.float64), sy[cy, cx].astype(np.float64), cnt[cy, cx].astype(np.float64),
                    None)
        r = max(k, 2 if self.params.line_normals else 0)
        d = np.arange(-r, r + 1)
        dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
        yy, xx = cy[:, None] + dy[None, :], cx[:, None] + dx[None, :]  # (U, (2r + 1)^2) neighbours
        inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        yy, xx = np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)
        c = np.where(inside, cnt[yy, xx], 0).astype(np.float64)
        # offsets from the requested cell's corner: a neighbour (+i, +j) cells away adds count * (i, j) * res
        ax = np.where(inside, sx[yy, xx], 0) + c * (dx * res)[None, :]
        ay = np.where(inside, sy[yy, xx], 0) + c * (dy * res)[None, :]
        if k > 0:
            m = ((np.abs(dy) <= k) & (np.abs(dx) <= k)).astype(np.float64)
            out = (ax @ m, ay @ m, c @ m)
        else:
            centre = dy.size // 2
            out = (ax[:, centre], ay[:, centre], c[:, centre])
        nrm = None
        if self.params.line_normals:
            m5 = ((np.abs(dy) <= 2) & (np.abs(dx) <= 2)).astype(np.float64)
            cs = np.where(c > 0, c, 1.0)
            n5 = c @ m5
            ns = np.where(n5 > 0, n5, 1.0)
            mx, my = (ax @ m5) / ns, (ay @ m5) / ns
            cxx = ((ax * ax / cs) @ m5) / ns - mx * mx
            cyy = ((ay * ay / cs) @ m5) / ns - my * my
            cxy = ((ax * ay / cs) @ m5) / ns - mx * my
            half_tr, diff = 0.5 * (cxx + cyy), 0.5 * (cxx - cyy)
            rad = np.sqrt(diff * diff + cxy * cxy)
            lmax, lmin = half_tr + rad, half_tr - rad
            theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # direction of the wall
            line = (n5 >= 3) & (lmax > (0.5 * res) ** 2) & (lmin < self.params.line_ratio * lmax)
            nrm = (-np.sin(theta), np.cos(theta), line)
        return out[0], out[1], out[2], nrm

    def install(self, arrays: FieldArrays) -> None:
        """Make computed arrays the current field."""
        inputs = arrays.inputs
        self.center = inputs.center
        self.generation = inputs.generation
        self.resolution = inputs.resolution
        self.fine, self.coarse, self.n_occupied = arrays.fine, arrays.coarse, arrays.n_occupied
        self.vx, self.vy = arrays.vx, arrays.vy
        if arrays.fine is not None:
            self.shape = arrays.shape
            self.origin = inputs.crop_origin - self.params.pad * inputs.resolution

    def log_likelihood(self, xy: np.ndarray) -> np.ndarray:
        """Log-likelihood (n,) of end points at map-frame positions xy (n, 2) (m), as the matcher's fine stage
        scores them: the vector to the nearest wall point interpolated bilinearly between cell centres (or,
        with ``vectors`` off, the likelihood itself), then the Gaussian of its length plus the floor. Points
        off the field get the floor. Raises RuntimeError before the first rebuild."""
        if self.fine is None:
            raise RuntimeError("the likelihood field has not been built yet (rebuild it from the grid first)")
        p = self.params
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        h, w = self.shape
        g = (xy - self.origin) / self.resolution - 0.5  # cell centres at integer coordinates
        x0, y0 = np.floor(g[:, 0]), np.floor(g[:, 1])
        ax, ay = g[:, 0] - x0, g[:, 1] - y0
        inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
        base = np.where(inside, y0 * w + x0, 0).astype(np.int64)
        corners = ((0, (1 - ax) * (1 - ay)), (1, ax * (1 - ay)), (w, (1 - ax) * ay), (w + 1, ax * ay))
        floor = float(np.log(p.p_floor))
        if self.vx is not None:
            vx = sum(c * self.vx[base + d] for d, c in corners)
            vy = sum(c * self.vy[base + d] for d, c in corners)
            out = np.log(np.exp(-0.5 * (vx * vx + vy * vy) / p.sigma_hit ** 2) + p.p_floor)
        else:
            out = sum(c * self.fine[base + d] for d, c in corners)
        return np.where(inside, out, floor)

    def wall_vectors(self, xy: np.ndarray) -> np.ndarray:
        """Vectors (n, 2) (m) from map-frame points xy (n, 2) to their nearest wall point, interpolated
        bilinearly as in :meth:`log_likelihood`; NaN off the field or without ``FieldParams.vectors``."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.full(xy.shape, np.nan)
        if self.vx is None:
            return out
        h, w = self.shape
        g = (xy - self.origin) / self.resolution - 0.5
        x0, y0 = np.floor(g[:, 0]), np.floor(g[:, 1])
        ax, ay = g[:, 0] - x0, g[:, 1] - y0
        inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
        base = np.where(inside, y0 * w + x0, 0).astype(np.int64)
        corners = ((0, (1 - ax) * (1 - ay)), (1, ax * (1 - ay)), (w, (1 - ax) * ay), (w + 1, ax * ay))
        vx = sum(c * self.vx[base + d] for d, c in corners)
        vy = sum(c * self.vy[base + d] for d, c in corners)
        out[inside] = np.stack([vx, vy], axis=1)[inside]
        return out

    def needs_rebuild(self, occupancy: OccupancyGrid, xy: np.ndarray, margin: float) -> bool:
        """True when the field was never built, the grid grew or ``xy`` (m) came within ``margin`` (m) of
        the crop's edge."""
        if self.fine is None or occupancy.grid.generation != self.generation:
            return True
        return bool(np.max(np.abs(np.asarray(xy) - self.center)) > self.params.half_size - margin)
