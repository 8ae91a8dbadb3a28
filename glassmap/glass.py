"""The temporary glass map and the glass confidence map (docs/method.md sections 4 and 5).

The temporary glass map is a layer of the shared :class:`~glassmap.grid.MapGrid` (default name ``"glass"``)
holding log-odds of "the object in this cell is glass" (float32, 0 = p 0.5 = no evidence, clamped to
[l_min, l_max]). It grows with the grid. The glass confidence map is its probability on the cells that are
occupied in the latest occupancy grid, NaN elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .grid import MapGrid, OccupancyGrid
from .registration import Aggregation, WindowEvidence, bayes_update, update_with_evidence


@dataclass(frozen=True)
class GlassParams:
    """Limits of the glass-map update (dimensionless log-odds / probabilities).

    l_min, l_max: clamp of the log-odds (+-4.6 = p 0.01 / 0.99) so that a cell can change its mind;
    p_clip: classifier outputs are clipped to [p_clip, 1 - p_clip] before the update;
    undecided: a confidence within 0.5 +- undecided counts as "undecided" (neither glass nor not glass).
    """

    l_min: float = -4.6
    l_max: float = 4.6
    p_clip: float = 1e-3
    undecided: float = 0.01

    def __post_init__(self) -> None:
        if not self.l_min < 0 < self.l_max:
            raise ValueError(f"GlassParams needs l_min < 0 < l_max, got {self.l_min}, {self.l_max}")
        if not 0 < self.p_clip < 0.5:
            raise ValueError(f"GlassParams.p_clip must be in (0, 0.5), got {self.p_clip}")


class GlassMap:
    """Temporary glass map stored as log-odds in the layer ``layer`` of ``grid``."""

    def __init__(self, grid: MapGrid, params: GlassParams = GlassParams(), layer: str = "glass") -> None:
        self.grid = grid
        self.params = params
        self.layer = layer
        if layer not in grid.layer_names:
            grid.add_layer(layer, 0.0, np.float32)
        self.updates = 0  # number of update() calls that changed something

    @property
    def log_odds(self) -> np.ndarray:
        """(H, W) float32 log-odds (the current array: the grid replaces it when it grows)."""
        return self.grid[self.layer]

    def probability(self) -> np.ndarray:
        """p(glass) per cell, (H, W) float32; 0.5 where no evidence."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def update(self, flat: np.ndarray, delta: np.ndarray) -> None:
        """Eq. 7 in log-odds: add ``delta`` to the unique flat cells ``flat`` and clamp."""
        if flat.size == 0:
            return
        bayes_update(self.log_odds, flat, delta, self.params.l_min, self.params.l_max)
        self.updates += 1

    def update_evidence(self, evidence: WindowEvidence, aggregation: Aggregation = "scan") -> int:
        """Eq. 7 with one scan's registration evidence (:func:`~glassmap.registration.window_evidence`),
        aggregated per cell (``"scan"``: mean, ``"beam"``: sum): the same as :meth:`update` with
        ``aggregate(registration_observations(...))``, in one compiled pass. Returns the cells updated."""
        n = update_with_evidence(self.log_odds, evidence, aggregation, self.params.l_min, self.params.l_max)
        if n:
            self.updates += 1
        return n

    def reset(self) -> None:
        self.log_odds[...] = 0.0
        self.updates = 0

    def glass_mask(self, threshold: float = 0.5) -> np.ndarray:
        """(H, W) bool: cells whose p(glass) exceeds ``threshold``."""
        return self.log_odds > np.float32(np.log(threshold / (1.0 - threshold)))

    def confidence_map(self, occupancy: OccupancyGrid) -> np.ndarray:
        """Glass confidence map: (H, W) float32 p(glass) on cells occupied in ``occupancy``, NaN elsewhere.

        ``occupancy`` must live on the same grid as this glass map.
        """
        if occupancy.grid is not self.grid:
            raise ValueError("the occupancy grid and the glass map must share one MapGrid")
        out = self.probability()
        out[~occupancy.occupied()] = np.nan
        return out

    def labels(self, occupancy: OccupancyGrid) -> np.ndarray:
        """Per-cell label of the confidence map, (H, W) int8: 1 glass, 0 not glass, -1 undecided
        (|p - 0.5| <= undecided) and -2 not occupied."""
        conf = self.confidence_map(occupancy)
        lab = np.full(conf.shape, -2, dtype=np.int8)
        occ = np.isfinite(conf)
        u = self.params.undecided
        lab[occ & (conf > 0.5 + u)] = 1
        lab[occ & (conf < 0.5 - u)] = 0
        lab[occ & (np.abs(conf - 0.5) <= u)] = -1
        return lab
