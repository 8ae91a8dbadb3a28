"""Map grids in the map frame: a growable stack of layers, and the log-odds occupancy grid.

Cell (col, row) = (ix, iy) covers map-frame x in [origin_x + ix*res, origin_x + (ix+1)*res) and likewise
for y; arrays are indexed ``layer[iy, ix]`` (row = y). Resolution in metres per cell (default 0.05 m).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .grid_jit import beam_walks, free_and_hit_update, scan_reach
from .grid_jit import hit_margins as _hit_margins

_NO_PROTECT = np.zeros(0, dtype=bool)
_NO_SEEN = np.zeros(0, dtype=np.uint8)


class MapGrid:
    """Grid geometry plus named layers that grow together as the robot explores.

    Layers are 2-D arrays of the grid's shape, each with its own fill value for new cells. Growth happens
    in blocks of ``grow_step_m`` so it is rare; after a growth, ``origin`` moves and every layer is padded.
    """

    def __init__(self, resolution: float = 0.05, origin: tuple[float, float] = (-10.0, -10.0),
                 shape: tuple[int, int] = (400, 400), grow_step_m: float = 10.0) -> None:
        if resolution <= 0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        self.resolution = float(resolution)
        self.origin = np.array(origin, dtype=np.float64)
        self.shape = (int(shape[0]), int(shape[1]))
        self.grow_step = max(1, int(round(grow_step_m / resolution)))
        self._layers: dict[str, np.ndarray] = {}
        self._fills: dict[str, float] = {}
        self.generation = 0  # incremented at every growth

    def add_layer(self, name: str, fill: float = 0.0, dtype=np.float32) -> np.ndarray:
        if name in self._layers:
            raise ValueError(f"layer {name!r} exists already")
        self._layers[name] = np.full(self.shape, fill, dtype=dtype)
        self._fills[name] = fill
        return self._layers[name]

    def __getitem__(self, name: str) -> np.ndarray:
        return self._layers[name]

    def __setitem__(self, name: str, value: np.ndarray) -> None:
        if value.shape != self.shape:
            raise ValueError(f"layer {name!r}: shape {value.shape} != grid shape {self.shape}")
        self._layers[name] = value

    @property
    def layer_names(self) -> list[str]:
        return list(self._layers)

    def copy(self, layers: list[str] | None = None) -> "MapGrid":
        """An independent copy of the geometry and of ``layers`` (default: all), e.g. to export or score
        the maps in another thread while this grid keeps changing."""
        names = self.layer_names if layers is None else list(layers)
        missing = [n for n in names if n not in self._layers]
        if missing:
            raise ValueError(f"no layer(s) {missing} in the grid (layers: {self.layer_names})")
        out = MapGrid(self.resolution, (float(self.origin[0]), float(self.origin[1])), (0, 0),
                      self.grow_step * self.resolution)
        out.shape = self.shape
        out.generation = self.generation
        for n in names:
            out._layers[n] = self._layers[n].copy()
            out._fills[n] = self._fills[n]
        return out

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """Map-frame points (..., 2) in metres -> integer cells (..., 2) as (ix, iy); may lie outside."""
        return np.floor((np.asarray(xy) - self.origin) / self.resolution).astype(np.int64)

    def cell_to_world(self, cells: np.ndarray) -> np.ndarray:
        """Cells (..., 2) as (ix, iy) -> map-frame centres (..., 2) in metres."""
        return self.origin + (np.asarray(cells) + 0.5) * self.resolution

    def in_bounds(self, cells: np.ndarray) -> np.ndarray:
        c = np.asarray(cells)
        return (c[..., 0] >= 0) & (c[..., 0] < self.shape[1]) & (c[..., 1] >= 0) & (c[..., 1] < self.shape[0])

    def ensure_contains(self, xy_min: np.ndarray | tuple[float, float],
                        xy_max: np.ndarray | tuple[float, float]) -> bool:
        """Grow every layer so the map-frame box [xy_min, xy_max] (m, (x, y)) lies inside. Returns True if it grew."""
        x0, y0, x1, y1 = float(xy_min[0]), float(xy_min[1]), float(xy_max[0]), float(xy_max[1])
        if not (math.isfinite(x0) and math.isfinite(y0) and math.isfinite(x1) and math.isfinite(y1)):
            raise ValueError("ensure_contains needs finite coordinates")
        # the usual case, the box inside already: the cells of world_to_cell in Python floats (same operations)
        ox, oy, r = float(self.origin[0]), float(self.origin[1]), self.resolution
        h, w = self.shape
        if (math.floor((x0 - ox) / r) >= 0 and math.floor((y0 - oy) / r) >= 0
                and math.floor((x1 - ox) / r) <= w - 1 and math.floor((y1 - oy) / r) <= h - 1):
            return False
        lo = self.world_to_cell(np.asarray(xy_min, dtype=np.float64))
        hi = self.world_to_cell(np.asarray(xy_max, dtype=np.float64))
        pad_left = self._blocks(-lo[0])
        pad_bottom = self._blocks(-lo[1])
        pad_right = self._blocks(hi[0] - (w - 1))
        pad_top = self._blocks(hi[1] - (h - 1))
        if not (pad_left or pad_bottom or pad_right or pad_top):
            return False
        shape = (h + pad_bottom + pad_top, w + pad_left + pad_right)
        for name, arr in self._layers.items():
            # np.zeros (calloc) zeroes only what the allocator cannot hand over zeroed (fresh pages are, until
            # first written); np.pad wrote the whole new area while the scans waited
            fill = self._fills[name]
            grown = np.zeros(shape, arr.dtype) if fill == 0 else np.full(shape, fill, arr.dtype)
            grown[pad_bottom:pad_bottom + h, pad_left:pad_left + w] = arr
            self._layers[name] = grown
        self.origin = self.origin - np.array([pad_left, pad_bottom]) * self.resolution
        self.shape = shape
        self.generation += 1
        return True

    def _blocks(self, cells_missing: int) -> int:
        return 0 if cells_missing <= 0 else int(np.ceil(cells_missing / self.grow_step)) * self.grow_step


@dataclass(frozen=True)
class OccupancyParams:
    """Log-odds increments and limits of the occupancy update (dimensionless log-odds).

    l_occ: added at a beam's end point cell; l_free: added to cells the beam crossed (once per scan);
    l_min/l_max clamp; occ_threshold/free_threshold classify probabilities; max_free_range (m) caps how
    far a beam clears space (long beams are less trustworthy, and glass lets beams through);
    no_return_range (m) is how far a beam with no return (+inf) clears: 0 by default, because near glass
    "no return" usually means the pulse was reflected away, not that the space is empty; hit_margin (m):
    a beam with a return at the edge of a surface clears space only up to this far short of its end point
    (at least one cell); surface_margin (m): the same for a beam inside a continuous surface, i.e. whose
    neighbours EDGE_BEAMS either side both have returns less than EDGE_CHORD apart (at least one cell).

    Why a margin of several cells: range noise spreads a surface's end points over a band a cell or two
    deep, and a beam meeting the surface obliquely runs through that band for a long way before its end
    point (depth / cos(incidence)). Clearing up to one cell short of the end point, the beams that
    measured long erase the band's cells nearest to the sensor while the cells behind the surface keep
    their hits: surfaces lean away from where they were seen, scan matching pushes the robot towards what
    it looks at and a map built from matched poses comes out stretched along the route. Where the beams
    meet a continuous surface, neighbouring beams re-mark the band, and a long margin there leaves the
    surface's free side unknown instead (maps shrink); the band is lost at a surface's edges (range jumps,
    long range, grazing incidence), hence the long margin there only.
    """

    l_occ: float = 0.85
    l_free: float = -0.4
    l_min: float = -4.0
    l_max: float = 4.0
    occ_threshold: float = 0.65
    free_threshold: float = 0.35
    max_free_range: float = 20.0
    no_return_range: float = 0.0
    hit_margin: float = 0.2
    surface_margin: float = 0.1


EDGE_BEAMS = 3
"""A beam is inside a surface when the end points this many beams either side of it both exist..."""
EDGE_CHORD = 0.3
"""... and are less than this far apart (m)."""


def hit_margins(c: np.ndarray, s: np.ndarray, ranges: np.ndarray, hit: np.ndarray, edge: float,
                surface: float) -> np.ndarray:
    """Per beam, how far short of its end point it stops clearing (m): ``surface`` for a beam inside a
    continuous surface (see :class:`OccupancyParams`), ``edge`` otherwise. c, s (n,): the beams' direction
    cosines and sines (any one frame); ranges (n,) m; hit (n,) bool: beams with a return."""
    f64 = np.float64
    return _hit_margins(np.ascontiguousarray(c, f64), np.ascontiguousarray(s, f64), np.ascontiguousarray(ranges, f64),
                        np.ascontiguousarray(hit, np.bool_), float(edge), float(surface), EDGE_BEAMS, EDGE_CHORD)


class OccupancyGrid:
    """Log-odds occupancy grid on a :class:`MapGrid` layer ``"occupancy"`` (0 = unknown)."""

    LAYER = "occupancy"

    def __init__(self, grid: MapGrid | None = None, params: OccupancyParams = OccupancyParams()) -> None:
        self.grid = grid if grid is not None else MapGrid()
        self.params = params
        if self.LAYER not in self.grid.layer_names:
            self.grid.add_layer(self.LAYER, 0.0, np.float32)
        self._seen = _NO_SEEN  # scratch of integrate(): one byte per cell, kept between scans

    def __getstate__(self) -> dict:  # the scratch does not travel (copies, process pools)
        return {**self.__dict__, "_seen": _NO_SEEN}

    @property
    def log_odds(self) -> np.ndarray:
        return self.grid[self.LAYER]

    def probability(self) -> np.ndarray:
        """P(occupied) per cell, (H, W) float32; 0.5 where unknown."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def occupied(self) -> np.ndarray:
        return self.probability() > self.params.occ_threshold

    def free(self) -> np.ndarray:
        return self.probability() < self.params.free_threshold

    def unknown(self) -> np.ndarray:
        p = self.probability()
        return (p >= self.params.free_threshold) & (p <= self.params.occ_threshold)

    def integrate(self, laser_pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray,
                  range_max: float = 30.0,
                  protect: np.ndarray | Callable[[], np.ndarray] | None = None) -> int:
        """Update from one scan. laser_pose (3,) = laser (x, y, yaw) in the map frame; angles (n,) rad in
        the laser frame; ranges (n,) m (NaN invalid, +inf no return: neither marks anything occupied;
        +inf clears up to ``no_return_range``).

        protect: optional (H, W) bool mask of cells that free-space updates must not lower (e.g. cells the
        glass map believes are glass: beams pass through glass at oblique incidence), or a callable that
        returns it; the callable is evaluated after the grid has grown to hold this scan. Returns the
        number of beams used.
        """
        return self.integrate_scan(laser_pose, angles, ranges, range_max, protect)[0]

    def integrate_scan(self, laser_pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray,
                       range_max: float = 30.0,
                       protect: np.ndarray | Callable[[], np.ndarray] | None = None) -> tuple[int, np.ndarray]:
        """:meth:`integrate` (same arguments), returning also the scan's map-frame end points (2, n) m (x row,
        y row; the laser position for beams without a return within ``range_max``)."""
        pose, ranges, c, s = self._scan_directions(laser_pose, angles, ranges)
        p = self.params
        hit, clear, free_len, ends, n_clear, box = scan_reach(c, s, ranges, pose[0], pose[1], float(range_max),
                                                              p.max_free_range, p.no_return_range)
        if not n_clear:
            return 0, ends
        self._grow_to(box)
        g = self.grid
        w = g.shape[1]

        if callable(protect):
            protect = protect()
        if protect is not None and protect.shape != g.shape:
            raise ValueError(f"protect mask shape {protect.shape} != grid shape {g.shape} (pass a callable "
                             "to have it evaluated after the grid grows)")

        # Free space: samples every 0.7 cell along each clearing beam (ragged: each beam only up to its own
        # length), stopping hit_margin or surface_margin (at least one cell) short of a hit; each cell crossed
        # is lowered once per scan, each hit cell then raised once (glassmap/grid_jit.py).
        step = 0.7 * g.resolution
        ox, oy = float(g.origin[0]), float(g.origin[1])
        dx, dy, counts, hit_cells = beam_walks(c, s, ranges, hit, clear, free_len, ends, ox, oy, g.resolution, w,
                                               step, max(p.hit_margin, g.resolution),
                                               max(p.surface_margin, g.resolution), EDGE_BEAMS, EDGE_CHORD)
        lo = self.log_odds
        fx = np.float32((pose[0] - ox) / g.resolution)
        fy = np.float32((pose[1] - oy) / g.resolution)
        if self._seen.shape[0] != lo.size:
            self._seen = np.zeros(lo.size, np.uint8)
        free_and_hit_update(lo.reshape(-1), _NO_PROTECT if protect is None else protect.reshape(-1), self._seen,
                            w, fx, fy, dx, dy, counts, np.float32(step), np.float32(p.l_free), hit_cells,
                            np.float32(p.l_occ), np.float32(p.l_min), np.float32(p.l_max))
        return n_clear, ends

    def ensure_scan_extent(self, laser_pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray,
                           range_max: float = 30.0) -> bool:
        """Grow the grid to everything :meth:`integrate` would touch for this scan (same arguments), e.g.
        before writing per-end-point layers. Returns True if it grew."""
        pose, ranges, c, s = self._scan_directions(laser_pose, angles, ranges)
        p = self.params
        n_clear, box = scan_reach(c, s, ranges, pose[0], pose[1], float(range_max), p.max_free_range,
                                  p.no_return_range)[4:]
        if not n_clear:
            return False
        generation = self.grid.generation
        self._grow_to(box)
        return self.grid.generation != generation

    @staticmethod
    def _scan_directions(laser_pose, angles, ranges) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Validated arrays of one scan: pose (3,), ranges (n,) m and the beam directions (cos, sin) (n,) in
        the map frame."""
        angles = np.asarray(angles, dtype=np.float64)
        ranges = np.ascontiguousarray(ranges, dtype=np.float64)
        if angles.shape != ranges.shape:
            raise ValueError(f"angles {angles.shape} and ranges {ranges.shape} differ in shape")
        pose = np.asarray(laser_pose, dtype=np.float64)
        if pose.shape != (3,) or not all(math.isfinite(v) for v in pose.tolist()):
            raise ValueError(f"laser_pose must be 3 finite numbers, got {laser_pose!r}")
        yaw = pose[2] + angles
        return pose, ranges, np.cos(yaw), np.sin(yaw)

    def _grow_to(self, box: np.ndarray) -> None:
        """Grow the grid to the box (x min, y min, x max, y max) m of :func:`~glassmap.grid_jit.scan_reach`
        with a 1 m margin."""
        x0, y0, x1, y1 = box.tolist()
        self.grid.ensure_contains((x0 - 1.0, y0 - 1.0), (x1 + 1.0, y1 + 1.0))

    def save_pgm_yaml(self, stem: str) -> tuple[str, str]:
        """Write ``stem.pgm`` + ``stem.yaml`` in the ROS map_server format (trinary, 254 free, 0 occupied,
        205 unknown; image row 0 = top = highest y). Returns the two paths."""
        import os

        prob = self.probability()
        img = np.full(prob.shape, 205, dtype=np.uint8)
        img[prob > self.params.occ_threshold] = 0
        img[prob < self.params.free_threshold] = 254
        img = img[::-1]
        pgm, yaml = stem + ".pgm", stem + ".yaml"
        with open(pgm, "wb") as f:
            f.write(b"P5\n%d %d\n255\n" % (img.shape[1], img.shape[0]))
            f.write(img.tobytes())
        with open(yaml, "w") as f:
            f.write(f"image: {os.path.basename(pgm)}\nmode: trinary\nresolution: {self.grid.resolution}\n"
                    f"origin: [{self.grid.origin[0]:.4f}, {self.grid.origin[1]:.4f}, 0.0]\nnegate: 0\n"
                    f"occupied_thresh: {self.params.occ_threshold}\nfree_thresh: {self.params.free_threshold}\n")
        return pgm, yaml
