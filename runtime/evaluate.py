"""Score an online glass confidence map against a simulated world's blueprint (METHOD.md section 6).

Same rules as the paper's experiment in :mod:`glassmap.eval.trial`: the blueprint's wall/glass cells that
were seen (hit by at least one returned beam, from the simulator's truth) and lie within ``eval_radius`` of
a glass cell are evaluated; a cell is correct when its map label (``GlassMap.labels``: glass, not glass,
undecided, not occupied) agrees with the blueprint; undecided, not occupied or never registered count as
errors. The score is :func:`glassmap.eval.metrics.score_map`.

``seen`` comes from the emulated devices (:mod:`runtime.devices` records the blueprint cells the simulated
laser hit); without it the cells the map observed (known in the occupancy grid) stand in for it.
``tolerance`` > 0 lets a blueprint cell take the label of the nearest occupied map cell within that many
cells (0, the default, is the paper's per-cell rule).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class MapEvaluation:
    error: float
    glass_recall: float
    false_glass_rate: float
    unregistered: float
    n_cells: int
    n_glass: int
    n_wall: int
    seen_from: str = "simulator"

    def describe(self) -> str:
        return (f"classification error against the blueprint: {100 * self.error:.1f} % of {self.n_cells} wall/glass "
                f"cells near glass ({self.n_glass} glass, {self.n_wall} wall); glass recall "
                f"{100 * self.glass_recall:.1f} %, false glass on walls {100 * self.false_glass_rate:.1f} %, "
                f"unregistered or undecided {100 * self.unregistered:.1f} %")


def _on_grid(arr: np.ndarray, origin: np.ndarray, target_origin: np.ndarray, shape: tuple[int, int],
             resolution: float, fill) -> np.ndarray:
    """``arr`` (grid with corner ``origin``) cut / padded onto a grid with corner ``target_origin``, ``shape``."""
    out = np.full(shape, fill, dtype=arr.dtype)
    off = np.rint((np.asarray(target_origin) - np.asarray(origin)) / resolution).astype(int)  # (x, y) cells
    h, w = shape
    y0, x0 = max(0, -off[1]), max(0, -off[0])
    y1, x1 = min(h, arr.shape[0] - off[1]), min(w, arr.shape[1] - off[0])
    if y1 > y0 and x1 > x0:
        out[y0:y1, x0:x1] = arr[y0 + off[1]:y1 + off[1], x0 + off[0]:x1 + off[0]]
    return out


def evaluate_map(processor, world, *, seen: np.ndarray | None = None, eval_radius: float = 1.5,
                 tolerance: int = 0) -> MapEvaluation:
    """Score ``processor.mapper`` (a :class:`runtime.processor.MappingProcessor`) against ``world``.

    seen: (H, W) bool on ``Blueprint.from_world(world, resolution)``'s grid, or None (see module docstring)."""
    from glassmap.eval.metrics import score_map
    from glassmap.eval.trial import evaluation_mask
    from glassmap.sim.blueprint import Blueprint

    mapper = processor.mapper
    g = mapper.grid
    bp = Blueprint.from_world(world, resolution=g.resolution)
    labels = mapper.glass.labels(mapper.occupancy)
    if tolerance > 0:
        occ = labels > -2
        if occ.any():
            dist, (iy, ix) = ndimage.distance_transform_edt(~occ, return_indices=True)
            near = dist <= tolerance
            labels = np.where(near, labels[iy, ix], labels).astype(np.int8)
    lab = _on_grid(labels, g.origin, bp.origin, bp.labels.shape, g.resolution, np.int8(-2))
    seen_from = "simulator"
    if seen is None or seen.shape != bp.labels.shape:
        known = _on_grid(~mapper.occupancy.unknown(), g.origin, bp.origin, bp.labels.shape, g.resolution, False)
        seen = ndimage.binary_dilation(known, iterations=2)
        seen_from = "map"
    mask = evaluation_mask(bp.labels, seen, bp.resolution, eval_radius)
    s = score_map(lab, bp.labels, mask)
    return MapEvaluation(s.error, s.glass_recall, s.false_glass_rate, s.unregistered, s.n_cells, s.n_glass,
                         s.n_wall, seen_from)
