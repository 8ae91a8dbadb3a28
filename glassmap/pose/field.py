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

from dataclasses import dataclass, replace

import numpy as np

from glassmap.grid import OccupancyGrid
from glassmap.pose.field_jit import (cells_of_walls, changed_cells, forward_maximum, forward_maximum_at, near_cells,
                                     neighbour_sums, renew_nearest, unique_cells, wall_vectors)


FAR = 10.0  # m: the vector stored where no wall is within the cut-off (the likelihood there is the floor)


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
    nearest wall point."""

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
    nearest: np.ndarray | None = None  # (h, w) of the crop: flat index of each cell's nearest occupied cell, -1
    counts: np.ndarray | None = None  # copy of the crop's end-point counts the arrays were computed from


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
        self.arrays: FieldArrays | None = None  # what is installed, for :meth:`refresh`
        self._marks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # scratch of :meth:`update`

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

    def refresh(self, occupancy: OccupancyGrid,
                points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
        """Bring the field up to date with the grid on its own crop (centre kept): :meth:`update` of the
        installed arrays, the same field as a rebuild on that crop. Rebuilds when nothing is installed."""
        inputs = self.snapshot(occupancy, self.center, points, copy=False)
        self.install(self.compute(inputs) if self.arrays is None else self.update(self.arrays, inputs))

    def snapshot(self, occupancy: OccupancyGrid, center_xy: np.ndarray,
                 points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, copy: bool = True) -> FieldInputs:
        """Copy what :meth:`compute` needs from the grid (the crop around ``center_xy``): cheap, and the grid
        may change afterwards. ``copy`` False: the end-point layers are views of the grid's, which must not
        change until :meth:`compute` has run (the occupied cells are always copied)."""
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
        pts = None if (empty or points is None) else tuple(a[y0:y1, x0:x1] for a in points)
        if pts is not None and copy:
            pts = tuple(a.copy() for a in pts)
        return FieldInputs(occ, pts, np.asarray(center_xy, dtype=np.float64).copy(), g.generation, res,
                           g.origin + np.array([x0, y0]) * res)

    def compute(self, inputs: FieldInputs) -> FieldArrays:
        """The field arrays of a snapshot (pure: no shared state, safe in a worker thread)."""
        p = self.params
        occ = inputs.occupied
        if occ is None:
            return FieldArrays(inputs, None, None, (0, 0), 0)
        n_occupied = int(occ.sum())
        pad = p.pad
        field = np.full((occ.shape[0] + 2 * pad, occ.shape[1] + 2 * pad), self._floor32, dtype=np.float32)
        vx = vy = None
        if p.vectors:  # "far": a vector long enough that the Gaussian is below the floor's resolution
            vx = np.full(field.shape, np.float32(FAR), dtype=np.float32)
            vy = np.zeros(field.shape, dtype=np.float32)
        nearest = np.full(occ.shape, -1, dtype=np.int32)
        if n_occupied:
            # the cells within the cut of their nearest occupied cell (ny, nx)
            iy, ix, ny, nx, _, _ = near_cells(occ, self._cut2(inputs.resolution))
            nearest[iy, ix] = ny * occ.shape[1] + nx
            self._evaluate(inputs, iy, ix, ny, nx, field, vx, vy)
        f = p.coarse_factor
        coarse = forward_maximum(field, f)  # = ndimage.maximum_filter(field, f, origin=-(f // 2), mode="nearest")
        return FieldArrays(inputs, field.ravel(), coarse.ravel(), field.shape, n_occupied,
                           None if vx is None else vx.ravel(), None if vy is None else vy.ravel(), nearest,
                           None if inputs.points is None else inputs.points[2].copy())

    def update(self, arrays: FieldArrays, inputs: FieldInputs) -> FieldArrays:
        """The field of ``inputs`` from ``arrays``, the field of an earlier snapshot of the same crop: only
        the cells whose nearest occupied cell or whose wall point can have changed are computed again, and
        the result equals :meth:`compute` (inputs) to the last bit. The arrays of ``arrays`` are modified in
        place (``arrays`` is stale afterwards). Computes the whole field when the crop differs."""
        old, p = arrays.inputs, self.params
        if (arrays.fine is None or arrays.nearest is None or old.occupied is None or inputs.occupied is None
                or old.occupied.shape != inputs.occupied.shape or old.resolution != inputs.resolution
                or not np.array_equal(old.crop_origin, inputs.crop_origin)
                or (arrays.counts is None) != (inputs.points is None)):
            return self.compute(inputs)
        occ, nearest = inputs.occupied, arrays.nearest
        cnt, cnt_old = (occ, old.occupied.copy()) if arrays.counts is None else (inputs.points[2], arrays.counts)
        # the occupied cells added or cleared, and the cells whose end points changed (their count did; the
        # copy of the counts is brought up to date on the way; without end-point layers the wall points are
        # the occupied cells' centres, so those are the same cells)
        fy, fx, wy, wx = changed_cells(occ, old.occupied, cnt, cnt_old)
        # occupied count: the old one, plus the cells added, minus those cleared
        n_occupied = arrays.n_occupied + 2 * int(np.count_nonzero(occ[fy, fx])) - fy.size
        if fy.size == 0 and wy.size == 0:
            return replace(arrays, inputs=inputs)
        shape = arrays.shape
        pad, w = p.pad, occ.shape[1]
        field, coarse = arrays.fine.reshape(shape), arrays.coarse.reshape(shape)
        vx = None if arrays.vx is None else arrays.vx.reshape(shape)
        vy = None if arrays.vy is None else arrays.vy.reshape(shape)
        cut2 = self._cut2(inputs.resolution)
        mark, wall, mark_padded = self._scratch(occ.shape, shape)
        ay, ax = renew_nearest(occ, nearest, fy, fx, cut2, mark)  # the cells whose nearest cell may differ
        # and the others whose nearest cell's wall point or normal may differ (it pools the end points of the
        # (2 k + 1)^2 cells around it)
        k = max(p.pool, 2 if p.line_normals else 0)
        by, bx = cells_of_walls(nearest, wy, wx, k, int(np.sqrt(cut2)), ay * w + ax, mark, wall)
        cy, cx = np.concatenate([ay, by]), np.concatenate([ax, bx])
        near = nearest[cy, cx]
        gone = near < 0  # no occupied cell within the cut any more: the floor
        field[cy[gone] + pad, cx[gone] + pad] = self._floor32
        if vx is not None:
            vx[cy[gone] + pad, cx[gone] + pad] = np.float32(FAR)
            vy[cy[gone] + pad, cx[gone] + pad] = 0.0
        iy, ix = cy[~gone], cx[~gone]
        ny, nx = np.divmod(near[~gone], np.int32(w))
        self._evaluate(inputs, iy, ix, ny, nx, field, vx, vy)
        forward_maximum_at(field, coarse, cy + pad, cx + pad, p.coarse_factor, mark_padded)
        return FieldArrays(inputs, arrays.fine, arrays.coarse, shape, n_occupied, arrays.vx, arrays.vy, nearest,
                           arrays.counts)

    def _scratch(self, crop: tuple[int, int], padded: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All-False bool arrays of the crop's shape (two) and of the padded arrays' shape, kept between updates
        (the compiled passes leave them all False)."""
        if self._marks is None or self._marks[0].shape != crop or self._marks[2].shape != padded:
            self._marks = (np.zeros(crop, np.bool_), np.zeros(crop, np.bool_), np.zeros(padded, np.bool_))
        return self._marks

    @property
    def _floor32(self) -> np.float32:
        return np.float32(np.log(self.params.p_floor))

    def _cut2(self, res: float) -> int:
        """Squared cut-off (cells^2): beyond it the Gaussian is negligible against the floor (< 1e-4 in log),
        so only the cells that close to a wall are computed; the rest keep the floor."""
        p = self.params
        cut = p.sigma_hit * float(np.sqrt(-2.0 * np.log(1e-4 * p.p_floor))) + res
        cut_c = int(np.ceil(cut / res))
        return cut_c * cut_c

    def _evaluate(self, inputs: FieldInputs, iy: np.ndarray, ix: np.ndarray, ny: np.ndarray, nx: np.ndarray,
                  field: np.ndarray, vx: np.ndarray | None, vy: np.ndarray | None) -> None:
        """Write the log-likelihood (and the vectors) of the crop cells (iy, ix) whose nearest occupied cell
        is (ny, nx) (int32) into the padded arrays ``field``, ``vx``, ``vy``."""
        p = self.params
        res, occ, pad = inputs.resolution, inputs.occupied, p.pad
        ddy, ddx = ny - iy.astype(np.int32), nx - ix.astype(np.int32)  # offset to the nearest cell (cells)
        near = (iy + pad, ix + pad)
        points, pool = inputs.points, p.pool
        if points is None:  # no end-point layers: one point at the centre of each occupied cell (cell
            cnt0 = occ.astype(np.float64)  # centres carry no measurement bias: nothing to pool)
            points, pool = (0.5 * res * cnt0, 0.5 * res * cnt0, cnt0), 0
        # the wall point and normal are needed only at the occupied cells some cell is closest to
        u, inv = unique_cells(ny, nx, occ.shape[0], occ.shape[1])  # np.unique(flat, return_inverse=True)
        uy, ux = np.divmod(u, occ.shape[1])
        sx, sy, c, nrm = self._pooled(points, res, pool, uy, ux)
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
        d = np.hypot(ex, ey)
        field[near] = np.log(np.exp(-0.5 * (d / p.sigma_hit) ** 2) + p.p_floor).astype(np.float32)
        if vx is not None:
            vx[near] = ex
            vy[near] = ey

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
        cleared, puts the wall back at the mean of everything that was measured there. (The occupancy
        update's ``OccupancyParams.hit_margin`` keeps most of those cells from being cleared; pooling covers
        the rest.)

        Normals: the count-weighted scatter of the cell means in the 5 x 5 neighbourhood (long enough for a
        wall two cells thick to look like a line); where it is elongated (smaller eigenvalue below
        ``line_ratio`` times the larger) the cells are a straight wall and the field measures the distance
        along its normal. Measuring to the mean point of the nearest cell would add a saw-tooth along the
        wall (up to half a cell between two cells' points): a false along-wall constraint in corridors and a
        bias wherever the points sit unevenly in their cells."""
        sx, sy, cnt = (np.asarray(a) for a in points)
        if k <= 0 and not self.params.line_normals:
            return (sx[cy, cx].astype(np.float64), sy[cy, cx].astype(np.float64), cnt[cy, cx].astype(np.float64),
                    None)
        r = max(k, 2 if self.params.line_normals else 0)
        d = np.arange(-r, r + 1)
        dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))  # the (2r + 1)^2 neighbours, row-major
        # (U, (2r + 1)^2): counts, and offsets from the requested cell's corner (a neighbour (+i, +j) cells
        # away adds count * (i, j) * res), 0 off the grid
        c, ax, ay = neighbour_sums(sx, sy, cnt, cy, cx, r, res)
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
        self.arrays = arrays
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
        xy = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.vx is None:
            return np.full(xy.shape, np.nan)
        h, w = self.shape
        return wall_vectors(self.vx, self.vy, xy, float(self.origin[0]), float(self.origin[1]),
                            float(self.resolution), w, h)

    def needs_rebuild(self, occupancy: OccupancyGrid, xy: np.ndarray, margin: float) -> bool:
        """True when the field was never built, the grid grew or ``xy`` (m) came within ``margin`` (m) of
        the crop's edge."""
        if self.fine is None or occupancy.grid.generation != self.generation:
            return True
        return bool(np.max(np.abs(np.asarray(xy) - self.center)) > self.params.half_size - margin)
