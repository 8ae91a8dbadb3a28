"""The paper's experiment online: glass maps built from the pose estimator's poses and covariances.

Per trial (seed): simulate a run (scans 40 Hz, odometry 10 Hz), run the :class:`PoseEstimator` on every scan
(it builds the shared occupancy grid at its corrected poses), and on the scans ``glass_scans`` names feed the
glass mappers of each method (direct, robust 3x3, robust 5x5, ...) with the estimator's laser pose and per-beam
registration sigma. The mappers share the estimator's grid (each its own glass layer, ``glass_<method>``);
the estimator's occupancy update uses the first mapper's protect mask so that glass cells are kept as the
glass-map helper's trial does. Scoring is the glass-map helper's (``glassmap.eval``): blueprint wall/glass
cells seen by a returned beam and within ``eval_radius`` of glass.

With ``loop_closure`` the pose-graph back end (:class:`~glassmap.pose.backend.GraphBackEnd`) also takes every
key scan (with its p(glass)), and after the run each method's glass map is rebuilt from the key scans twice
(:func:`~glassmap.pose.corrected.rebuild_maps`, registration sigma relative to the map): at the front end's
poses (``<method>@keys``: no loop closure) and at the graph's optimised poses (``<method>@keys+lc``), so the
two differ only by the loop closures. The online maps (``<method>``) are scored as without it.

The glass path sees every ``glass_every``-th scan and every key scan: each is classified and its glass hits
are kept occupied in the shared grid. Which of them the online maps register (``glass_scans``): ``"keys"``
(default), each key scan as soon as the estimator has matched it, at its corrected pose, on the grid as it then
is; ``"every"``, every ``glass_every``-th scan, most of them placed by odometry since the last match (the
runtime's ``mapping.glass_scans`` = keys / all, with ``glass_every`` 1). ``compare_glass_scans`` adds, on the
same trial, maps ``<method>@<other>-online`` registered the other way; the grid and the trajectory are the same
for both.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from glassmap.pose.backend import BackEndConfig
from glassmap.pose.corrected import online_sigma
from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import FALSE_CLOSURE_XY, FALSE_CLOSURE_YAW, metrics, run_estimator


GLASS_SCANS = ("keys", "every")
"""Which scans an online glass map registers: the key scans, as each is matched, or every k-th scan."""


@dataclass(frozen=True)
class OnlineTrialConfig:
    """world / route: simulator world and route (None = default route); methods: names from
    ``glassmap.eval.trial.METHODS``; glass_every: the glass path sees every k-th scan (and every key scan;
    4 -> 10 Hz, the glass-map experiment's rate); eval_radius (m); estimator: the pose estimator's settings;
    sigma_scale: multiply the registration sigma (1 = as reported); glass_scans / compare_glass_scans: which
    scans the online maps register (``GLASS_SCANS``; module docstring); sigmas: where the online registration
    sigma comes from (:data:`~glassmap.pose.corrected.SIGMA_SOURCES`): the first feeds the methods' maps, each
    further one adds online maps ``<method>~<source>`` of the methods whose registration reads the sigma
    (robust; direct does not, so the trajectory and the first method's map are the same); loop_closure: also run the
    pose-graph back end (``backend``) and score the maps rebuilt from the key scans with and without its
    correction (module docstring)."""

    world: str = "office"
    route: str | None = None
    methods: tuple[str, ...] = ("direct", "robust3", "robust5")
    glass_every: int = 4
    glass_scans: str = "keys"
    compare_glass_scans: bool = False
    eval_radius: float = 1.5
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    sigma_scale: float = 1.0
    sigmas: tuple[str, ...] = ("map",)
    loop_closure: bool = False
    backend: BackEndConfig = field(default_factory=BackEndConfig)

    def __post_init__(self) -> None:
        if self.glass_scans not in GLASS_SCANS:
            raise ValueError(f"glass_scans must be one of {GLASS_SCANS}, got {self.glass_scans!r}")
        if self.glass_every < 1:
            raise ValueError(f"glass_every must be >= 1 (every k-th scan), got {self.glass_every}")


def run_online_trial(cfg: OnlineTrialConfig, seed: int, classifier=None, maps_out: dict | None = None) -> list[dict]:
    """One trial; returns one row per method (classification error and friends + pose metrics). ``maps_out``:
    a dict that receives the blueprint's labels (``"truth"``: 1 wall, 2 glass), the cells scored
    (``"evaluated"``) and each map's labels on the blueprint's cells under its method name (as
    :func:`glassmap.eval.metrics.score_map` takes them)."""
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
    backend = None
    key_index: list[int] = []  # run scan index of each key scan handed to the back end
    if cfg.loop_closure:
        from glassmap.pose.backend import GraphBackEnd

        backend = GraphBackEnd(cfg.backend, cfg.estimator.likelihood.sigma_hit)

    def on_scan(i, scan, est_pose, est):
        if not state:
            mappers = {}
            for m in cfg.methods:
                mc = MapperConfig(layer=f"glass_{m}", **METHODS[m])
                if mc.protect != "hits" or not mc.glass_hits_occupy:
                    raise ValueError(f"method {m!r} needs its own occupancy grid; the online experiment shares "
                                     "the estimator's grid (use direct / robust3 / robust5 / -endpoint / -beam)")
                mappers[m] = GlassMapper(est.occupancy, mc, classifier=classifier)
            for src in cfg.sigmas[1:]:
                for m in cfg.methods:
                    if METHODS[m]["registration"] != "direct":
                        mappers[f"{m}~{src}"] = GlassMapper(est.occupancy, MapperConfig(
                            layer=f"glass_{m}~{src}", **METHODS[m]), classifier=classifier)
            state["mappers"] = mappers
            state["other_kind"] = kind = next(g for g in GLASS_SCANS if g != cfg.glass_scans)
            state["other_mappers"] = {f"{m}@{kind}-online": GlassMapper(est.occupancy, MapperConfig(
                layer=f"glass_{m}@{kind}-online", **METHODS[m]), classifier=classifier)
                for m in (cfg.methods if cfg.compare_glass_scans else ())}
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
        mappers = state["mappers"]
        first = next(iter(mappers.values()))
        other_mappers = state["other_mappers"]
        beams = None
        is_key = est.stats.last_keyframe and est.last_key_scan is not None
        if backend is not None and is_key:
            beams, use = first.classify(scan)
            backend.add(replace(est.last_key_scan, scan=scan, p_glass=np.where(use, beams.p_glass, np.nan),
                                incidence=beams.incidence))
            key_index.append(i)
        now = {"keys": is_key, "every": i % cfg.glass_every == 0}
        if not any(now.values()):
            return
        lp = est.laser_pose(est_pose)
        if beams is None:
            beams, use = first.classify(scan)
        first.mark_glass_hits(beams, use, scan, lp)  # on every scan the glass path sees, as the runtime
        main = now[cfg.glass_scans]
        other = bool(other_mappers) and now[state["other_kind"]]
        if not main and not other:
            return
        sigma = {src: cfg.sigma_scale * online_sigma(est, est_pose, scan.ranges, src) for src in cfg.sigmas}
        s0 = sigma[cfg.sigmas[0]]
        if main:
            sigmas.append(float(np.nanmedian(s0)) if np.isfinite(s0).any() else np.nan)
            for name, mp in mappers.items():
                s = sigma[name.split("~")[1] if "~" in name else cfg.sigmas[0]]
                mp.register(beams, use & np.isfinite(s), scan, lp, s)
        if other:
            for mp in other_mappers.values():
                mp.register(beams, use & np.isfinite(s0), scan, lp, s0)

    from glassmap.grid import MapGrid, OccupancyGrid

    occ = OccupancyGrid(MapGrid(bp.resolution, origin=tuple(bp.origin), shape=bp.labels.shape, grow_step_m=5.0),
                        cfg.estimator.occupancy)
    traj, est = run_estimator(run, cfg.estimator, on_scan=on_scan, occupancy=occ)
    pm = metrics(traj, run)
    mask = evaluation_mask(bp.labels, seen, bp.resolution, cfg.eval_radius)
    common = dict(seed=seed, world=cfg.world)
    pose_cols = dict(ate_rmse=pm.ate_rmse, ate_max=pm.ate_max, nees_mean=pm.nees_mean,
                     sigma_median=float(np.nanmedian(sigmas)), n_scans=pm.scans)
    maps = [(m, "online", mp) for m, mp in state["mappers"].items()]
    maps += [(m, m.split("@")[1], mp) for m, mp in state["other_mappers"].items()]
    lc_cols: dict = {}
    if backend is not None:
        from glassmap.grid import MapGrid
        from glassmap.pose.corrected import rebuild_maps

        truth = run.scan_true_poses[np.asarray(key_index, dtype=np.int64)]
        front = np.array([k.pose for k in backend.keys])
        optimised = backend.poses()
        lc_cols = dict(key_scans=len(backend), closures=len(backend.closures),
                       false_closures=_false_closures(backend.closures, truth),
                       keys_ate=_ate(front, truth), keys_lc_ate=_ate(optimised, truth))
        for kind, poses in (("keys", front), ("keys+lc", optimised)):
            for m in cfg.methods:
                grid = MapGrid(bp.resolution, origin=tuple(bp.origin), shape=bp.labels.shape, grow_step_m=5.0)
                _, gm = rebuild_maps(backend.keys, poses, cfg.estimator.occupancy, mapper=MapperConfig(
                    layer=f"glass_{m}", **METHODS[m]), grid=grid)
                maps.append((f"{m}@{kind}", kind, gm))
    rows = []
    if maps_out is not None:
        maps_out.update(truth=bp.labels, evaluated=mask)
    for name, kind, mp in maps:
        labels = _on_blueprint(mp, bp)
        if maps_out is not None:
            maps_out[name] = labels
        s = score_map(labels, bp.labels, mask)
        rows.append(dict(common, method=name, maps=kind, error=s.error, error_occupied=s.error_occupied,
                         glass_recall=s.glass_recall, false_glass_rate=s.false_glass_rate,
                         unregistered=s.unregistered, n_cells=s.n_cells, **pose_cols, **lc_cols,
                         seconds=time.perf_counter() - t0))
    return rows


def _ate(poses: np.ndarray, truth: np.ndarray) -> float:
    """RMSE (m) of the positions ``poses`` (N, 3) against ``truth`` (N, 3)."""
    if not len(poses):
        return float("nan")
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))


def _false_closures(closures, truth: np.ndarray) -> int:
    """How many accepted closures are further than FALSE_CLOSURE_XY / _YAW from the truth (key-scan poses
    ``truth`` (N, 3)) in the directions they constrain."""
    bad = 0
    for c in closures:
        dxy, dyaw = c.error(truth[c.anchor], truth[c.node])
        bad += int(dxy > FALSE_CLOSURE_XY or dyaw > FALSE_CLOSURE_YAW)
    return bad


def _on_blueprint(mapper, bp) -> np.ndarray:
    """The mapper's glass labels on the blueprint's cells (-2 where its grid does not reach)."""
    lab = mapper.glass.labels(mapper.occupancy)
    h, w = bp.labels.shape
    off = np.rint((bp.origin - mapper.grid.origin) / bp.resolution).astype(int)
    sub = np.full((h, w), -2, dtype=lab.dtype)
    y0, x0 = max(off[1], 0), max(off[0], 0)
    y1, x1 = min(off[1] + h, lab.shape[0]), min(off[0] + w, lab.shape[1])
    if y1 > y0 and x1 > x0:
        sub[y0 - off[1]:y1 - off[1], x0 - off[0]:x1 - off[0]] = lab[y0:y1, x0:x1]
    return sub


MAP_KINDS = ("", "@keys-online", "@every-online", "@keys", "@keys+lc")  # method-name suffixes of the maps


def margins(summary: dict[str, dict[str, float]], base: str = "direct", other: str = "robust3",
            suffixes: tuple[str, ...] = MAP_KINDS) -> list[dict]:
    """For each map kind (method-name suffix) present in ``summary`` (:func:`glassmap.eval.experiment.summarise`
    rows): ``other``'s mean / worst / std of the error against ``base``'s, as relative gains (positive:
    ``other`` is lower), and whether ``other`` beats ``base`` in all three; ``maps`` names the kind, ``suffix``
    is its method-name suffix."""
    out = []
    for suf in suffixes:
        a, b = summary.get(base + suf), summary.get(other + suf)
        if a is None or b is None:
            continue
        gain = {k: (a[k] - b[k]) / a[k] if a[k] > 0 else float("nan") for k in ("mean", "worst", "std")}
        out.append(dict(maps=suf.lstrip("@") or "online", suffix=suf, base=base, other=other,
                        **{f"{k}_gain": v for k, v in gain.items()},
                        beats=all(b[k] < a[k] for k in ("mean", "worst", "std"))))
    return out


def paired(rows: list[dict], base: str, other: str) -> dict:
    """Trial by trial (rows with the same ``seed``): in how many of the ``n`` trials ``other``'s error is
    lower than ``base``'s (``wins``), and the mean of base - other (``diff``: positive = ``other`` lower,
    error fraction) with its standard error (``diff_se``; NaN for fewer than two trials)."""
    err = {(r["method"], str(r["seed"])): float(r["error"]) for r in rows}
    seeds = [s for (m, s) in err if m == base and (other, s) in err]
    d = np.array([err[(base, s)] - err[(other, s)] for s in seeds])
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
    return dict(n=int(d.size), wins=int((d > 0).sum()), diff=float(d.mean()) if d.size else float("nan"), diff_se=se)


def world_margins(rows: list[dict], base: str = "direct", others: tuple[str, ...] = ("robust3", "robust3~anchor"),
                  suffixes: tuple[str, ...] = MAP_KINDS) -> tuple[list[dict], list[dict]]:
    """Per world (the rows' ``world``) and per map kind: each of ``others``' margins over ``base``
    (:func:`margins`) and trial-by-trial figures (:func:`paired`: ``n``, ``wins``, ``diff``, ``diff_se``);
    and over the worlds, per (other, maps): the mean margin, the worst world's margin (lowest gain) and that
    world, how many worlds it beats ``base`` in mean, worst and std together, and its trials won of all."""
    from glassmap.eval.experiment import summarise

    per_world = []
    for world in dict.fromkeys(r["world"] for r in rows):
        in_world = [r for r in rows if r["world"] == world]
        summary = summarise(in_world)
        for other in others:
            for m in margins(summary, base, other, suffixes if "~" not in other else ("",)):
                per_world.append(dict(world=world, **m, **paired(in_world, base + m["suffix"], other + m["suffix"])))
    overall = []
    for key in dict.fromkeys((m["other"], m["maps"]) for m in per_world):
        ms = [m for m in per_world if (m["other"], m["maps"]) == key]
        row = dict(other=key[0], maps=key[1], worlds=len(ms), beats=sum(m["beats"] for m in ms),
                   wins=sum(m["wins"] for m in ms), trials=sum(m["n"] for m in ms))
        for k in ("mean", "worst", "std"):
            g = np.array([m[f"{k}_gain"] for m in ms])
            row[f"{k}_gain"] = float(np.nanmean(g))
            row[f"{k}_gain_worst"] = float(np.nanmin(g))
            row[f"{k}_gain_worst_world"] = ms[int(np.nanargmin(g))]["world"]
        overall.append(row)
    return per_world, overall
