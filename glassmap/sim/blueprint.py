"""Ground-truth blueprint: a world's segments rasterised on a grid, each cell free, wall (not glass) or glass.

Grid convention (as the occupancy grid): cell (row, col) covers map-frame x in
[origin_x + col * res, origin_x + (col + 1) * res) and y likewise with row; row index = y, column index = x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from glassmap.sim.world import World

FREE, WALL, GLASS = 0, 1, 2
"""Blueprint labels: free, wall / any non-glass obstacle, glass."""

COLORS = np.array([[255, 255, 255], [40, 40, 40], [220, 40, 40]], dtype=np.uint8)
"""RGB of FREE, WALL, GLASS in exported images."""


@dataclass
class Blueprint:
    """labels: (H, W) uint8 (0 free, 1 wall/not glass, 2 glass); origin: (2,) map-frame xy (m) of the corner
    of cell (0, 0); resolution: cell size (m)."""

    labels: np.ndarray
    origin: np.ndarray
    resolution: float

    @classmethod
    def from_world(cls, world: World, resolution: float = 0.05, margin: float = 1.0,
                   origin: tuple[float, float] | None = None, shape: tuple[int, int] | None = None) -> "Blueprint":
        """Rasterise ``world``. By default the grid covers the world's bounds plus ``margin`` (m) with its
        origin on a multiple of ``resolution``; pass ``origin`` and ``shape`` (H, W) to match another grid.

        A cell crossed by segments is GLASS when the length of glass inside it exceeds the length of other
        material (so mullions and wall junctions stay WALL), otherwise WALL.
        """
        if resolution <= 0:
            raise ValueError(f"resolution must be > 0 m, got {resolution}")
        (xmin, ymin), (xmax, ymax) = world.bounds
        if origin is None:
            org = np.array([math.floor((xmin - margin) / resolution) * resolution,
                            math.floor((ymin - margin) / resolution) * resolution])
        else:
            org = np.asarray(origin, dtype=np.float64)
        if shape is None:
            h = int(math.ceil((ymax + margin - org[1]) / resolution))
            w = int(math.ceil((xmax + margin - org[0]) / resolution))
        else:
            h, w = shape
        seg = world.segments
        length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
        step = resolution / 4
        n_samp = np.maximum(np.ceil(length / step).astype(np.int64), 1)
        sid = np.repeat(np.arange(len(seg)), n_samp)
        start = np.cumsum(n_samp) - n_samp
        frac = (np.arange(sid.size) - np.repeat(start, n_samp) + 0.5) / np.repeat(n_samp, n_samp)
        pts = seg[sid, 0] + frac[:, None] * (seg[sid, 1] - seg[sid, 0])
        wlen = (length / n_samp)[sid]
        col = np.floor((pts[:, 0] - org[0]) / resolution).astype(np.int64)
        row = np.floor((pts[:, 1] - org[1]) / resolution).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        flat = (row * w + col)[inside]
        glass = world.segment_is_glass[sid][inside]
        g_len = np.bincount(flat[glass], weights=wlen[inside][glass], minlength=h * w)
        o_len = np.bincount(flat[~glass], weights=wlen[inside][~glass], minlength=h * w)
        labels = np.where(g_len > o_len, GLASS, np.where(o_len > 0, WALL, FREE)).astype(np.uint8)
        return cls(labels=labels.reshape(h, w), origin=org, resolution=float(resolution))

    @property
    def shape(self) -> tuple[int, int]:
        return self.labels.shape  # type: ignore[return-value]

    def cell_of(self, xy) -> np.ndarray:
        """(..., 2) integer (row, col) of the cells containing map-frame points xy (..., 2) (m)."""
        xy = np.asarray(xy, dtype=np.float64)
        rc = np.floor((xy[..., ::-1] - self.origin[::-1]) / self.resolution)
        return rc.astype(np.int64)

    def to_rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 image with north up (row 0 of the image = the largest y)."""
        return COLORS[self.labels[::-1]]

    def save_png(self, path: str | Path) -> Path:
        """Write the blueprint as a PNG (free white, wall dark gray, glass red; north up)."""
        import matplotlib.image as mpimg

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        mpimg.imsave(path, self.to_rgb())
        return path
