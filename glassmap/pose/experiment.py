"""The paper's experiment online: glass maps built from the pose estimator's poses and covariances.

Per trial (seed): simulate a run (scans 40 Hz, odometry 10 Hz), run the :class:`PoseEstimator` on every scan
(it builds the shared occupancy grid at its corrected poses), and every ``glass_every``-th scan feed the glass
mappers of each method (direct, robust 3x3, robust 5x5, ...) with the estimator's laser pose and per-beam
registration sigma. The mappers share the estimator's grid (each its own glass layer, ``glass_<method>``);
the estimator's occupancy update uses the first mapper's protect mask so that glass cells are kept as the
glass-map helper's trial does. Scoring is the glass-map helper's (``glassmap.eval``): blueprint wall/glass
cells seen by a returned beam and within ``eval_radius`` of glass.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import metrics, run_estimator


@dataclass(frozen=True)
class OnlineTrialConfig:
    """world / route: simulator world and route (None = default route); methods: names from
    ``glassmap.eval.trial.METHODS``; glass_every: map glass on every k-th scan (4 -> 10 Hz, the glass-map
    experiment's rate); eval_radius (m); estimator: the pose estimator's settings; sigma_scale: multiply
    the registration sigma (1 = as reported)."""

    world: str = "office"
    route: str | None = None
    methods: tuple[str, ...] = ("direct", "robust3", "robust5")
    glass_every: int = 4
    eval_radius: float = 1.5
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    sigma_scale: float = 1.0


def run_online_trial(cfg: OnlineTrialConfig, seed: int, classifier=None) -> list[dict]:
    """One trial; returns one row per method (classification error and friends + pose metrics)."""
    from glassmap.eval.metrics import score_map
    from glassmap.eval.trial import METHODS, evaluation_mask
    from glassmap.mapping import GlassMapper, MapperConfig
    from glassmap.sim.blueprint import Blueprint
    from glassmap.sim.dataset import simulate_run
    from glassmap.sim.world import load_world

    t0 = time.perf_counter()
    world = load_world(cfg.world)
    run = simulate_run(world, cfg.route, seed=seed)
    bp = Blueprint.from_world(world, resolution=0.05)
    if classifier is None:
        from glassmap.classifier import GlassClassifier

        classifier = GlassClassifier.load_default()
    h, w = bp.labels.shape
    seen = np.zeros(bp.labels.shape, dtype=bool)
    state: dict = {}
    sigmas: list[float] = []

    def on_scan(i, scan, est_pose, est):
        if not state:
            mappers = {}
            for m in cfg.methods:
                mc = MapperConfig(layer=f"glass_{m}", **METHODS[m])
                if mc.protect != "hits" or not mc.glass_hits_occupy:
                    raise ValueError(f"method {m!r} needs its own occupancy grid; the online experiment shares "
                                     "the estimator's grid (use direct / robust3 / robust5 / -endpoint / -beam)")
                mappers[m] = GlassMapper(est.occupancy, mc, classifier=classifier)
            state["mappers"] = mappers
            first = next(iter(mappers.values()))
            est.protect_mask_fn = first.protect_mask
        # truth: blueprint cells seen by returned beams from the true pose
        lp_true = run.laser_poses[i]
        ret = np.isfinite(run.ranges[i]) & np.isfinite(run.true_range[i])
        ang = lp_true[2] + scan.angles[ret]
        ex = np.round(lp_true[0] + run.true_range[i][ret] * np.cos(ang), 6)
        ey = np.round(lp_true[1] + run.true_range[i][ret] * np.sin(ang), 6)
        cx = np.floor((ex - bp.origin[0]) / bp.resolution).astype(np.int64)
        cy = np.floor((ey - bp.origin[1]) / bp.resolution).astype(np.int64)
        ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        seen[cy[ok], cx[ok]] = True
        if i % cfg.glass_every:
            return
        mappers = state["mappers"]
        first = next(iter(mappers.values()))
        lp = est.laser_pose(est_pose)
        sigma = cfg.sigma_scale * est.registration_sigma(est_pose, scan.ranges)
        sigmas.append(float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else np.nan)
        beams, use = first.classify(scan)
        first.mark_glass_hits(beams, use, scan, lp)
        use = use & np.isfinite(sigma)
        for mp in mappers.values():
            mp.register(beams, use, scan, lp, sigma)

    from glassmap.grid import MapGrid, OccupancyGrid

    occ = OccupancyGrid(MapGrid(bp.resolution, origin=tuple(bp.origin), shape=bp.labels.shape, grow_step_m=5.0),
                        cfg.estimator.occupancy)
    traj, est = run_estimator(run, cfg.estimator, on_scan=on_scan, occupancy=occ)
    pm = metrics(traj, run)
    mask = evaluation_mask(bp.labels, seen, bp.resolution, cfg.eval_radius)
    rows = []
    for m, mp in state["mappers"].items():
        lab = mp.glass.labels(mp.occupancy)
        off = np.rint((bp.origin - mp.grid.origin) / bp.resolution).astype(int)
        sub = np.full((h, w), -2, dtype=lab.dtype)
        # the estimator's grid may not cover the whole blueprint: copy the overlap
        y0, x0 = max(off[1], 0), max(off[0], 0)
        y1, x1 = min(off[1] + h, lab.shape[0]), min(off[0] + w, lab.shape[1])
        if y1 > y0 and x1 > x0:
            sub[y0 - off[1]:y1 - off[1], x0 - off[0]:x1 - off[0]] = lab[y0:y1, x0:x1]
        s = score_map(sub, bp.labels, mask)
        rows.append(dict(seed=seed, world=cfg.world, method=m, error=s.error, error_occupied=s.error_occupied,
                         glass_recall=s.glass_recall, false_glass_rate=s.false_glass_rate,
                         unregistered=s.unregistered, n_cells=s.n_cells, ate_rmse=pm.ate_rmse, ate_max=pm.ate_max,
                         nees_mean=pm.nees_mean, sigma_median=float(np.nanmedian(sigmas)),
                         n_scans=pm.scans, seconds=time.perf_counter() - t0))
    return rows
