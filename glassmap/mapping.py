"""The per-scan glass path (docs/method.md sections 2-5): incidence angles, classifier, registration, update.

:class:`GlassMapper` owns (or shares) an occupancy grid and a temporary glass map on one
:class:`~glassmap.grid.MapGrid`. ``process`` takes one scan (laser frame), the laser pose in the map frame
and the registration sigma (metres), and updates the maps. All steps are vectorized over beams.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from .angles import AngleMethod, AngleParams, incidence_angles
from .glass import GlassMap, GlassParams
from .grid import MapGrid, OccupancyGrid
from .grid_jit import bounds, classified_beams, raise_end_cells, ranged_beams
from .registration import Aggregation, DecayRef, Method, nearest_occupied_cells, window_evidence
from .types import Scan

log = logging.getLogger(__name__)

_NO_MARKS = np.zeros(0, dtype=bool)

MAX_ABS_COORD = 1.0e4
"""Largest |x| or |y| (m) of a laser pose the mapper accepts; beyond it the grid would grow absurdly."""


class MappingInputError(ValueError):
    """A scan, pose or sigma given to the mapper is unusable (the message says which and why)."""


@dataclass(frozen=True)
class MapperConfig:
    """Settings of the glass path.

    angle_method: "split-merge" (default, chosen from `glassmap glass angles`) or "hough".
    registration: "direct" (nearest occupied cell only) or "robust" (k x k window, eq. 6).
    window: k (3 or 5). decay_ref: eq. 6 distance from c_hat_j ("cell", default) or from the end point.
    aggregation: "scan" (mean log-odds per cell per scan, default) or "beam" (every beam, the paper).
    search_radius: cells around the end-point cell searched for the nearest occupied cell c_hat_j.
    weights: classifier weights stem (path without suffix); None = the shipped default model (``context``).
        A model that reads echoes given a single-echo scan uses the shipped ``baseline`` model instead.
    protect: which cells free-space updates must not clear when this mapper updates the occupancy grid
        (beams pass through glass at oblique incidence, which is no evidence that the cell is free):
        "hits" (default) = cells where a beam classified as glass ended (layer ``<layer>_hits``),
        "glass" = cells the glass map believes are glass (p > protect_threshold), "none".
    glass_hits_occupy: a beam classified as glass (p > glass_hit_threshold) raises the occupancy log-odds of
        its end-point cell to at least OccupancyParams.l_occ. Glass is seen only near normal incidence and
        oblique beams pass through it, so by the time the first glass return arrives the pane's cells have
        usually been cleared (to l_min) by earlier pass-through beams; a pass-through is no evidence against
        glass, so the glass return restores the cell. Applied to the shared grid also when
        ``update_occupancy=False``.
    visibility: robust registration hands a beam's evidence to a window neighbour in proportion to the chance
        that the neighbour could have returned the beam: 1 for a cell that is not glass, and for glass the
        chance that a pane returns a beam at the beam's incidence angle, exp(-theta^2 / (2 w^2)) with w =
        ``glass_return_width`` (rad); the neighbour's current p(glass) weighs the two. (A wall is seen at
        every incidence, a pane only near normal incidence: without it, a wall's oblique beams erode the
        end of a pane next to it.) The centre cell c_hat_j always gets p(g_j).
    """

    angle_method: AngleMethod = "split-merge"
    angle_params: AngleParams = field(default_factory=AngleParams)
    registration: Method = "robust"
    window: int = 3
    decay_ref: DecayRef = "cell"
    aggregation: Aggregation = "scan"
    search_radius: int = 2
    weights: str | None = None
    glass: GlassParams = field(default_factory=GlassParams)
    protect: Literal["hits", "glass", "none"] = "hits"
    protect_threshold: float = 0.7
    glass_hits_occupy: bool = True
    glass_hit_threshold: float = 0.5
    layer: str = "glass"
    visibility: bool = False
    glass_return_width: float = math.radians(10.0)

    def __post_init__(self) -> None:
        if self.registration not in ("direct", "robust"):
            raise ValueError(f"registration must be 'direct' or 'robust', got {self.registration!r}")
        if self.window not in (1, 3, 5, 7):
            raise ValueError(f"window must be 3 or 5 (1 and 7 allowed for experiments), got {self.window}")
        if self.decay_ref not in ("cell", "endpoint"):
            raise ValueError(f"decay_ref must be 'cell' or 'endpoint', got {self.decay_ref!r}")
        if self.aggregation not in ("scan", "beam"):
            raise ValueError(f"aggregation must be 'scan' or 'beam', got {self.aggregation!r}")
        if self.protect not in ("hits", "glass", "none"):
            raise ValueError(f"protect must be 'hits', 'glass' or 'none', got {self.protect!r}")
        if self.search_radius < 0:
            raise ValueError(f"search_radius must be >= 0 cells, got {self.search_radius}")
        if not self.glass_return_width > 0:
            raise ValueError(f"glass_return_width must be > 0 rad, got {self.glass_return_width}")


@dataclass
class BeamGlass:
    """Per-beam result of one scan.

    p_glass: (n,) p(glass), NaN for beams without an angle (or otherwise unusable); incidence: (n,) rad, NaN
    if none. Counters: beams in the scan, with a usable range, with an incidence angle, classified,
    registered (contributed to the glass map), and skipped as bad (NaN range or intensity, bad sigma).
    """

    p_glass: np.ndarray
    incidence: np.ndarray
    n_beams: int = 0
    n_ranged: int = 0
    n_angle: int = 0
    n_classified: int = 0
    n_registered: int = 0
    n_bad: int = 0
    no_intensities: bool = False


class GlassMapper:
    """Builds the occupancy grid (optionally) and the temporary glass map, scan by scan."""

    def __init__(self, occupancy: OccupancyGrid | None = None, config: MapperConfig = MapperConfig(),
                 classifier=None) -> None:
        self.config = config
        self.occupancy = occupancy if occupancy is not None else OccupancyGrid()
        self.grid = self.occupancy.grid
        self.glass = GlassMap(self.grid, config.glass, layer=config.layer)
        self.hits_layer = config.layer + "_hits"
        if config.protect == "hits" and self.hits_layer not in self.grid.layer_names:
            self.grid.add_layer(self.hits_layer, False, np.bool_)
        if classifier is None:
            from .classifier import GlassClassifier

            classifier = (GlassClassifier.load(config.weights) if config.weights
                          else GlassClassifier.load_default())
        self.classifier = classifier
        self._fallback = None  # the baseline model, loaded at the first single-echo scan if needed
        self.scans = 0
        self.skipped_scans = 0
        self._occ_thr = float(math.log(self.occupancy.params.occ_threshold / (1 - self.occupancy.params.occ_threshold)))

    # -- stages --------------------------------------------------------------------------------------------
    def classify(self, scan: Scan, *, angles: np.ndarray | None = None) -> tuple[BeamGlass, np.ndarray]:
        """Incidence angles and p(glass) per beam (laser frame; needs no pose). Returns the result and the
        mask of beams that were classified. angles: ``scan.angles`` if the caller has them already."""
        a = scan.angles if angles is None else angles
        r = scan.ranges
        n = r.shape[0]
        rr, n_ranged, n_nan = ranged_beams(r, scan.geometry.range_min, scan.geometry.range_max)
        if n_ranged == 0:
            return BeamGlass(np.full(n, np.nan), np.full(n, np.nan), n_beams=n, n_bad=n_nan), np.zeros(n, dtype=bool)
        res = incidence_angles(a, rr, self.config.angle_method, self.config.angle_params)
        out = BeamGlass(np.full(n, np.nan), res.incidence, n_beams=n, n_ranged=n_ranged, n_bad=n_nan)
        if scan.intensities is None:
            out.n_angle = int(np.count_nonzero(np.isfinite(res.incidence)))
            out.no_intensities = True
            return out, np.zeros(n, dtype=bool)
        use, out.n_angle, n_bad, out.n_classified = classified_beams(res.incidence, scan.intensities, r)
        out.n_bad += n_bad
        if out.n_classified:
            out.p_glass[use] = self.classifier_for(scan).predict_scan(scan, res, use, angles=a)
        return out, use

    def classifier_for(self, scan: Scan):
        """The classifier for this scan: the configured one, or the shipped baseline when the configured one
        reads echoes and the scan has none (said once in the log)."""
        clf = self.classifier
        if scan.echoes is not None or not getattr(clf, "uses_echoes", False):
            return clf
        if self._fallback is None:
            from .classifier import FALLBACK_MODEL, GlassClassifier

            self._fallback = GlassClassifier.load_default(FALLBACK_MODEL)
            log.warning("single-echo scans: the %r glass classifier needs multi-echo scans, using the %r model "
                        "(f(intensity, distance, incidence)) instead", clf.model_name, FALLBACK_MODEL)
        return self._fallback

    def register(self, beams: BeamGlass, use: np.ndarray, scan: Scan, laser_pose: np.ndarray,
                 sigma: np.ndarray, *, ends: tuple[np.ndarray, np.ndarray] | None = None) -> int:
        """Registration + Bayesian update of the classified beams ``use`` against the current occupancy grid.
        ``sigma`` (n,) metres per beam; ``ends``: :func:`end_points` of ``use`` at ``laser_pose`` if the caller
        has them already. Returns the number of beams registered."""
        n_use = int(np.count_nonzero(use))
        if not n_use:
            return 0
        cfg = self.config
        ex, ey = end_points(laser_pose, scan.angles, scan.ranges, use) if ends is None else ends
        g = self.grid
        margin = (cfg.window // 2 + cfg.search_radius + 2) * g.resolution
        g.ensure_contains(*_box(ex, ey, margin))
        ends = np.empty((ex.shape[0], 2))
        ends[:, 0] = ex
        ends[:, 1] = ey
        cells, _ = nearest_occupied_cells(ends, g.origin, g.resolution, self.occupancy.log_odds, self._occ_thr,
                                          cfg.search_radius)
        ev = window_evidence(beams.p_glass[use], ends, cells, sigma[use], g.origin, g.resolution,
                             method=cfg.registration, k=cfg.window, decay_ref=cfg.decay_ref, p_clip=cfg.glass.p_clip)
        if cfg.visibility:  # a beam without an incidence angle is registered as by eq. 6
            theta = beams.incidence[use]
            returns = np.exp(-(theta * theta) / (2.0 * cfg.glass_return_width ** 2))
            ev = replace(ev, returns=np.where(np.isfinite(returns), returns, 1.0))
        self.glass.update_evidence(ev, cfg.aggregation)
        return n_use

    def protect_mask(self) -> np.ndarray | None:
        """(H, W) bool cells that free-space updates must not clear (``MapperConfig.protect``), or None."""
        if self.config.protect == "hits":
            return self.grid[self.hits_layer]
        if self.config.protect == "glass":
            return self.glass.glass_mask(self.config.protect_threshold)
        return None

    def integrate(self, scan: Scan, pose: np.ndarray, *, angles: np.ndarray | None = None) -> np.ndarray:
        """Occupancy update of one scan at the laser pose (map frame) with the configured protection.
        angles: ``scan.angles`` if the caller has them already. Returns the map-frame end points (2, n) m of
        the scan's beams (x row, y row; :meth:`~glassmap.grid.OccupancyGrid.integrate_scan`)."""
        # the mask is taken after integrate() has grown the grid to hold the scan
        a = scan.angles if angles is None else angles
        return self.occupancy.integrate_scan(pose, a, scan.ranges, scan.geometry.range_max,
                                             protect=self.protect_mask)[1]

    def mark_glass_hits(self, beams: BeamGlass, use: np.ndarray, scan: Scan, laser_pose: np.ndarray, *,
                        ends: tuple[np.ndarray, np.ndarray] | None = None) -> int:
        """For beams classified as glass (p > glass_hit_threshold): raise the occupancy log-odds of their
        end-point cells to at least ``l_occ`` (``MapperConfig.glass_hits_occupy``) and record the cells in the
        ``<layer>_hits`` layer (``protect="hits"``). ``ends``: :func:`end_points` of ``use`` at ``laser_pose``
        if the caller has them already (else those of the glass beams are computed). Returns the number of
        such beams."""
        glass = use & (beams.p_glass > self.config.glass_hit_threshold)  # p_glass is NaN off the classified beams
        n_sel = int(np.count_nonzero(glass))
        if not n_sel:
            return 0
        if ends is None:
            x, y = end_points(laser_pose, scan.angles, scan.ranges, glass)
        else:
            glass = glass[use]
            x, y = ends[0][glass], ends[1][glass]
        g = self.grid
        g.ensure_contains(*_box(x, y, 1.0))
        # the cells of MapGrid.world_to_cell; log-odds raised as by np.maximum (compiled: glassmap/grid_jit.py),
        # never above l_max (OccupancyGrid.integrate clamps only the cells it changes)
        marks = self.grid[self.hits_layer].reshape(-1) if self.config.protect == "hits" else _NO_MARKS
        op = self.occupancy.params
        raise_end_cells(self.occupancy.log_odds.reshape(-1), marks, x, y, float(g.origin[0]), float(g.origin[1]),
                        g.resolution, g.shape[1], np.float32(min(op.l_occ, op.l_max)), self.config.glass_hits_occupy)
        return n_sel

    def warm_up(self, scan: Scan) -> None:
        """Run the per-scan path once on ``scan`` at the map origin on a scratch grid, leaving this mapper's
        maps and counters alone: the first call of the network and of each compiled kernel in a process
        costs tens of milliseconds, which would otherwise delay the first real scans."""
        grid = MapGrid(resolution=self.grid.resolution)
        scratch = GlassMapper(OccupancyGrid(grid, self.occupancy.params), self.config, classifier=self.classifier)
        scratch._fallback = self._fallback
        beams = scratch.process(scan, np.zeros(3), 0.05)
        # the glass hits' kernel runs only once a beam looks like glass, which this scan need not show
        n = scan.ranges.shape[0]
        scratch.mark_glass_hits(BeamGlass(np.ones(n), beams.incidence, n_beams=n), np.isfinite(scan.ranges), scan,
                                np.zeros(3))
        self._fallback = scratch._fallback

    # -- the per-scan path ---------------------------------------------------------------------------------
    def process(self, scan: Scan, laser_pose: np.ndarray, sigma: float | np.ndarray | None, *,
                update_occupancy: bool = True, occupancy_pose: np.ndarray | None = None,
                register: bool = True) -> BeamGlass:
        """One scan: incidence angles, p(glass) (one batched network call), occupancy update (unless the caller
        did it already: ``update_occupancy=False``), glass hits, registration and Bayesian update (unless
        ``register=False``: then ``sigma`` is not used and may be None).

        laser_pose: (3,) laser (x, y, yaw) in the map frame (m, rad). sigma: registration sigma (m), scalar or
        per beam (n,). occupancy_pose: the laser pose for the occupancy update and the glass hits it keeps
        (default ``laser_pose``; the experiment builds a consistent map from the true poses this way while
        registering at the estimated ones). Raises :class:`MappingInputError` for a bad pose or sigma
        (nothing is changed); beams with NaN range / intensity or NaN sigma are skipped and counted in
        ``n_bad``.
        """
        pose = self._checked_pose(laser_pose)
        occ_pose = pose if occupancy_pose is None else self._checked_pose(occupancy_pose)
        n = scan.ranges.shape[0]
        sig = self._checked_sigma(sigma, n) if register else None
        self.scans += 1
        if n == 0:
            self.skipped_scans += 1
            return BeamGlass(np.zeros(0), np.zeros(0))
        angles = scan.angles
        beams, use = self.classify(scan, angles=angles)
        if sig is not None and not (finite_sigma := np.isfinite(sig)).all():
            beams.n_bad += int(np.count_nonzero(use & ~finite_sigma))
            use &= finite_sigma
        # the end points of the beams ``use`` at occ_pose: the occupancy update's, when it ran
        ends = None
        if update_occupancy:
            pts = self.integrate(scan, occ_pose, angles=angles)
            ends = (pts[0][use], pts[1][use])
        if self.config.glass_hits_occupy or self.config.protect == "hits":
            self.mark_glass_hits(beams, use, scan, occ_pose, ends=ends)
        if register:
            beams.n_registered = self.register(beams, use, scan, pose, sig, ends=ends if occ_pose is pose else None)
        if beams.n_ranged == 0:
            self.skipped_scans += 1
        return beams

    @staticmethod
    def _checked_sigma(sigma, n: int) -> np.ndarray:
        """The registration sigma (n,) m per beam from a scalar or (n,) array; MappingInputError if not >= 0."""
        sig = np.asarray(sigma, dtype=np.float64)
        if sig.ndim == 0:
            sig = np.full(n, float(sig))
        elif sig.shape != (n,):
            raise MappingInputError(f"sigma must be a scalar or one value per beam ({n}), got shape {sig.shape}")
        if (sig < 0).any():
            raise MappingInputError("sigma must be >= 0 m")
        return sig

    @staticmethod
    def _checked_pose(laser_pose) -> np.ndarray:
        pose = np.asarray(laser_pose, dtype=np.float64)
        x, y, yaw = pose.tolist() if pose.shape == (3,) else (math.nan,) * 3  # Python floats: cheaper checks
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)):
            raise MappingInputError(f"laser_pose must be 3 finite numbers (x m, y m, yaw rad), got {laser_pose!r}")
        if abs(x) > MAX_ABS_COORD or abs(y) > MAX_ABS_COORD:
            raise MappingInputError(f"laser pose {pose[:2]} m is more than {MAX_ABS_COORD:.0f} m from the map "
                                    "origin; refusing to grow the map that far (check the pose source)")
        return pose

    # -- outputs -------------------------------------------------------------------------------------------
    def copy_maps(self) -> "MapCopy":
        """Copies of the occupancy grid and the glass map (picklable: no classifier), to publish or export in
        another thread or process while this mapper keeps mapping. Costs a copy of two layers."""
        grid = self.grid.copy([OccupancyGrid.LAYER, self.config.layer])
        return MapCopy(OccupancyGrid(grid, self.occupancy.params), GlassMap(grid, self.glass.params, self.config.layer))

    def confidence_map(self) -> np.ndarray:
        """(H, W) float32 p(glass) on occupied cells, NaN elsewhere."""
        return self.glass.confidence_map(self.occupancy)

    def export(self, out_dir: str, stem: str = "glass_map", scale: int = 2, crop: bool = True) -> dict[str, str]:
        """Write the maps (see :func:`export_maps`). Returns the paths."""
        return export_maps(self.occupancy, self.glass, out_dir, stem, scale, crop)


def end_points(laser_pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray,
               use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame end points x, y (m) of the beams ``use`` (n,) bool, given the laser pose (3,) in the map
    frame, the beam angles (n,) rad in the laser frame and the ranges (n,) m."""
    ang = laser_pose[2] + angles[use]
    rr = ranges[use]
    return laser_pose[0] + rr * np.cos(ang), laser_pose[1] + rr * np.sin(ang)


def _box(x: np.ndarray, y: np.ndarray, margin: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """Lower and upper corners (m) of the box around the n >= 1 points (x, y) grown by ``margin`` (m)."""
    x0, y0, x1, y1 = bounds(x, y).tolist()
    return (x0 - margin, y0 - margin), (x1 + margin, y1 + margin)


@dataclass
class MapCopy:
    """A copy of the occupancy grid and the glass map on their own grid (from :meth:`GlassMapper.copy_maps`)."""

    occupancy: OccupancyGrid
    glass: GlassMap

    @property
    def grid(self):
        return self.occupancy.grid

    def confidence_map(self) -> np.ndarray:
        """(H, W) float32 p(glass) on occupied cells, NaN elsewhere."""
        return self.glass.confidence_map(self.occupancy)

    def export(self, out_dir: str, stem: str = "glass_map", scale: int = 2, crop: bool = True) -> dict[str, str]:
        """Write the maps (see :func:`export_maps`). Returns the paths."""
        return export_maps(self.occupancy, self.glass, out_dir, stem, scale, crop)


def export_maps(occupancy: OccupancyGrid, glass: GlassMap, out_dir: str, stem: str = "glass_map", scale: int = 2,
                crop: bool = True) -> dict[str, str]:
    """Write the glass confidence map: ``stem.png`` (paper colours, each cell scale x scale pixels, cropped to
    the explored area unless ``crop=False``), ``stem_glass.npy`` (p(glass) on occupied cells, NaN elsewhere,
    the whole grid; row = y, column = x), ``stem_glass.json`` (origin, resolution of the npy), and the
    occupancy map ``stem.pgm`` + ``stem.yaml`` (ROS map_server). Returns the paths."""
    from .render import glass_confidence_png

    os.makedirs(out_dir, exist_ok=True)
    base = os.path.join(out_dir, stem)
    grid = occupancy.grid
    conf = glass.confidence_map(occupancy)
    png = glass_confidence_png(base + ".png", conf, occupancy.free(), scale=scale, crop=crop)
    npy = base + "_glass.npy"
    np.save(npy, conf)
    meta = base + "_glass.json"
    with open(meta, "w") as f:
        json.dump({"origin": grid.origin.tolist(), "resolution": grid.resolution,
                   "shape": list(conf.shape), "index": "array[iy, ix], cell (0,0) corner at origin",
                   "values": "p(glass) on occupied cells, NaN elsewhere"}, f, indent=2)
    pgm, yaml = occupancy.save_pgm_yaml(base)
    return {"png": png, "npy": npy, "json": meta, "pgm": pgm, "yaml": yaml}
