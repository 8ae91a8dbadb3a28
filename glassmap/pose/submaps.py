"""Submaps: runs of consecutive key scans, each with its own local occupancy grid and likelihood field.

A submap's frame is the front-end pose of its first key scan (its anchor node in the pose graph). Within a
submap the front end's poses are locally consistent (a metre of travel), so its scans are placed at their
front-end poses relative to the anchor; the pose graph moves submaps as rigid bodies. Short submaps keep
the front end's drift out of what a closure matches against: the drift inside one submap is in no edge of
the graph, so a closure inherits it (docs/loop-closure.md, "Shorter submaps"). A loop-closure candidate is
matched against a group of neighbouring old submaps placed by the pose graph; their grid and likelihood
field are built only then (:meth:`SubmapStore.field`) and the last few are cached, so memory holds scans,
not grids.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from glassmap.grid import MapGrid, OccupancyGrid, OccupancyParams
from glassmap.pose.field import FieldParams, LikelihoodField
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.motion import compose, relative


@dataclass(frozen=True)
class SubmapConfig:
    """length (m): travel after which a submap is closed and a new one starts; range_max (m): beams used to
    build a submap's grid; resolution (m); cache: built fields kept; field: likelihood-field settings
    (``half_size`` m: the crop, enough for a submap and the beams from it)."""

    length: float = 1.0
    range_max: float = 12.0
    resolution: float = 0.05
    cache: int = 4
    field: FieldParams = FieldParams(half_size=10.0)


@dataclass
class Submap:
    """index; nodes: pose-graph nodes of its key scans (the first is the anchor); local (k, 3): their poses
    in the anchor's frame; scans: the key scans; start / end (m): path length at its first / last node;
    closed: no more scans will be added."""

    index: int
    nodes: list[int] = field(default_factory=list)
    local: list[np.ndarray] = field(default_factory=list)
    scans: list[KeyScan] = field(default_factory=list)
    start: float = 0.0
    end: float = 0.0
    closed: bool = False

    @property
    def anchor(self) -> int:
        return self.nodes[0]

    def centre(self) -> np.ndarray:
        """Mean position (2,) of its key scans in the anchor's frame (m)."""
        return np.mean(np.asarray(self.local)[:, :2], axis=0)


class SubmapStore:
    """Submaps in order; ``add`` files each key scan into the open one."""

    def __init__(self, config: SubmapConfig = SubmapConfig()) -> None:
        self.config = config
        self.submaps: list[Submap] = []
        self._fields: OrderedDict[tuple, tuple[LikelihoodField, OccupancyGrid]] = OrderedDict()
        self._anchor_pose: np.ndarray | None = None  # front-end pose of the open submap's anchor

    def add(self, node: int, key: KeyScan, path_length: float) -> Submap:
        """File key scan ``key`` (pose-graph node ``node``, ``path_length`` m travelled so far); returns its
        submap (a new one when the open one is long enough)."""
        open_ = self.submaps[-1] if self.submaps and not self.submaps[-1].closed else None
        if open_ is not None and path_length - open_.start >= self.config.length:
            open_.closed = True
            open_ = None
        if open_ is None:
            open_ = Submap(len(self.submaps), start=path_length)
            self.submaps.append(open_)
            self._anchor_pose = np.asarray(key.pose, dtype=np.float64)
        open_.nodes.append(node)
        open_.local.append(relative(self._anchor_pose, key.pose))
        open_.scans.append(key)
        open_.end = path_length
        return open_

    def field(self, group: list[Submap], anchors: np.ndarray) -> tuple[LikelihoodField, OccupancyGrid]:
        """The likelihood field and occupancy grid of the submaps ``group`` placed at ``anchors`` (k, 3): each
        one's anchor pose in the frame of the first one's anchor (built on first use, cached by the group's
        indices; call :meth:`clear_cache` when the poses change)."""
        key = tuple(sm.index for sm in group)
        hit = self._fields.get(key)
        if hit is not None:
            self._fields.move_to_end(key)
            return hit
        cfg = self.config
        half = cfg.field.half_size
        occ = OccupancyGrid(MapGrid(cfg.resolution, origin=(-half, -half), shape=(int(2 * half / cfg.resolution),) * 2),
                            OccupancyParams())
        ends = []
        for sm, a in zip(group, np.asarray(anchors, dtype=np.float64)):
            for pose, k in zip(sm.local, sm.scans):
                r = np.where(k.ranges > cfg.range_max, np.inf, k.ranges)
                lp = compose(compose(a, pose), k.mount)
                occ.integrate(lp, k.angles, r, min(k.range_max, cfg.range_max))
                hit = np.isfinite(r)
                ang = lp[2] + k.angles[hit]
                ends.append(lp[:2] + r[hit, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1))
        f = LikelihoodField(cfg.field)
        f.rebuild(occ, group[0].centre(), _hit_layers(occ.grid, np.concatenate(ends) if ends else np.zeros((0, 2))))
        self._fields[key] = (f, occ)
        while len(self._fields) > cfg.cache:
            self._fields.popitem(last=False)
        return f, occ

    def clear_cache(self) -> None:
        """Forget the built fields (after the pose graph moved the submaps)."""
        self._fields.clear()


def _hit_layers(g: MapGrid, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell sums of end-point offsets from the cell corner (x, y, m) and counts, the sub-cell wall
    layers :meth:`LikelihoodField.rebuild` takes."""
    sx, sy, n = (np.zeros(g.shape, dtype=np.float32) for _ in range(3))
    cells = g.world_to_cell(xy)
    ok = g.in_bounds(cells)
    cells, xy = cells[ok], xy[ok]
    off = xy - (g.origin + cells * g.resolution)
    flat = cells[:, 1] * g.shape[1] + cells[:, 0]
    for lay, v in ((sx, off[:, 0]), (sy, off[:, 1]), (n, np.ones(len(flat)))):
        np.add.at(lay.reshape(-1), flat, v.astype(np.float32))
    return sx, sy, n
