"""Likelihood field for scan matching, derived from the occupancy grid (map frame).

Each cell holds the log-likelihood of a beam end point falling in it:
``log(exp(-d^2 / (2 sigma_hit^2)) + p_floor)`` with d the distance (m) to the nearest occupied cell; the
floor stands for everything the map does not explain (people, glass seen for the first time, unknown
space). A second array holds, per cell, the maximum over the ``f x f`` block starting at that cell: looking
a point up there gives an upper bound of the fine score over a coarse translation step (multi-resolution
search). The field covers a square crop around the robot and is rebuilt from the grid when asked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from glassmap.grid import OccupancyGrid


@dataclass(frozen=True)
class FieldParams:
    """sigma_hit (m): end-point spread around a wall; p_floor: uniform floor (relative to the peak 1);
    occupied_log_odds: cells above it count as walls; half_size (m): half-width of the crop around the
    robot; pad (cells): border of floor cells so that lookups near the edge stay in the array;
    coarse_factor: cells per coarse step of the multi-resolution search."""

    sigma_hit: float = 0.05
    p_floor: float = 0.05
    occupied_log_odds: float = 0.6
    half_size: float = 14.0
    pad: int = 64
    coarse_factor: int = 4


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


class LikelihoodField:
    """Fine and coarse (block-max) log-likelihood arrays over a crop of the occupancy grid.

    ``origin`` is the map-frame (x, y) of the corner of cell (0, 0) of the arrays, ``resolution`` the grid's.
    Arrays are indexed ``[iy, ix]`` and stored flat for fast gathers.
    """

    def __init__(self, params: FieldParams = FieldParams()) -> None:
        self.params = params
        self.fine: np.ndarray | None = None
        self.coarse: np.ndarray | None = None
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
            if inputs.points is None:
                d = np.hypot(ddx, ddy) * res
            else:
                sx, sy, cnt = inputs.points
                c = cnt[ny, nx]
                has = c > 0
                cs = np.where(has, c, 1)
                mx = np.where(has, sx[ny, nx] / cs, 0.5 * res)  # mean offset in the cell (m)
                my = np.where(has, sy[ny, nx] / cs, 0.5 * res)
                d = np.hypot((ddx - 0.5) * res + mx, (ddy - 0.5) * res + my)
            inner[near] = np.log(np.exp(-0.5 * (d / p.sigma_hit) ** 2) + p.p_floor).astype(np.float32)
        f = p.coarse_factor
        coarse = ndimage.maximum_filter(field, size=f, origin=-(f // 2), mode="nearest")
        return FieldArrays(inputs, field.ravel(), coarse.ravel(), field.shape, n_occupied)

    def install(self, arrays: FieldArrays) -> None:
        """Make computed arrays the current field."""
        inputs = arrays.inputs
        self.center = inputs.center
        self.generation = inputs.generation
        self.resolution = inputs.resolution
        self.fine, self.coarse, self.n_occupied = arrays.fine, arrays.coarse, arrays.n_occupied
        if arrays.fine is not None:
            self.shape = arrays.shape
            self.origin = inputs.crop_origin - self.params.pad * inputs.resolution

    def needs_rebuild(self, occupancy: OccupancyGrid, xy: np.ndarray, margin: float) -> bool:
        """True when the field was never built, the grid grew or ``xy`` (m) came within ``margin`` (m) of
        the crop's edge."""
        if self.fine is None or occupancy.grid.generation != self.generation:
            return True
        return bool(np.max(np.abs(np.asarray(xy) - self.center)) > self.params.half_size - margin)
