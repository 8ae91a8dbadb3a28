"""Evaluation of the pose estimator on simulated runs: trajectory error and covariance consistency.

With a pose-graph back end (``backend``) also: the same errors of the corrected poses (online, and
optimised after the run), accepted loop closures and how many of them are false against the truth.

Metrics per run (positions in metres, the map frame anchored at the true start pose, so no alignment):
ATE RMSE and max of the base position at the scan times, final drift (position error at the last scan), the
same for raw wheel odometry (dead reckoning from the true start), mean yaw error, and the NEES
e^T P^-1 e (3 dof, x, y, yaw; ideal mean 3) with the share of scans inside the 95 % bound (chi-square,
3 dof: 7.815).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from glassmap.pose.backend import corrected_estimate
from glassmap.pose.estimator import EstimatorConfig, PoseEstimator
from glassmap.pose.motion import compose, relative
from glassmap.types import wrap_angle

CHI2_3DOF_95 = 7.815
FALSE_CLOSURE_XY = 0.05  # m: a loop closure further than this from the truth (where it constrains) is false
FALSE_CLOSURE_YAW = float(np.radians(1.0))


@dataclass
class Trajectory:
    """Per-scan estimates of one run: stamps (S,), poses (S, 3) base in the map frame, covs (S, 3, 3),
    truth (S, 3), odom (S, 3) raw odometry mapped into the map frame from the true start pose,
    t_core (S,) seconds of prediction + matching + covariance + fusion, t_field / t_integrate (S,), key (S,)
    bool: key scans (matched and integrated; see EstimatorConfig.keyframe_*). With a pose-graph back end:
    corrected (S, 3) each scan's pose as the back end corrected it at that time (online) and corrected_covs
    (S, 3, 3) its covariance (``corrected_estimate``), optimised (S, 3)
    after the whole run (each scan moved with its last key scan), closures the accepted loop closures,
    closure_truth_error (C, 2) each closure's error against the truth (m, rad), t_backend (K,) seconds of the
    back end per key scan, closure_checks: loop-closure matches tried, chain_unscaled: closures that took
    ``BackEndConfig.chain_scale`` off the sequential edges between their nodes."""

    stamps: np.ndarray
    poses: np.ndarray
    covs: np.ndarray
    truth: np.ndarray
    odom: np.ndarray
    t_core: np.ndarray
    t_field: np.ndarray
    t_integrate: np.ndarray
    matched: int
    no_match: int
    gated: int
    key: np.ndarray
    corrected: np.ndarray | None = None
    corrected_covs: np.ndarray | None = None
    optimised: np.ndarray | None = None
    closures: list | None = None
    closure_truth_error: np.ndarray | None = None
    t_backend: np.ndarray | None = None
    closure_checks: int = 0
    chain_unscaled: int = 0
    lost_events: int = 0
    ambiguous_events: int = 0


@dataclass
class RunMetrics:
    world: str
    route: str
    seed: int
    scans: int
    length_m: float
    ate_rmse: float
    ate_max: float
    final_drift: float
    yaw_rmse_deg: float
    odom_ate_rmse: float
    odom_ate_max: float
    odom_final_drift: float
    nees_mean: float
    nees_median: float
    inside_95: float
    # the mean NEES split by scan kind: key scans (matched and integrated; their covariance is the chain's) and
    # the scans between them (the chain's plus odometry since the key scan); yaw alone (1 dof) for each
    nees_key_mean: float
    nees_between_mean: float
    yaw_nees_key_mean: float
    yaw_nees_between_mean: float
    # the mean NEES of each axis alone (1 dof each, ideal 1), over all scans: the position error along and
    # across the true heading, and the heading; a 3-dof mean in band can hide a position covariance too wide
    # and a heading too narrow that compensate
    along_nees_mean: float
    cross_nees_mean: float
    yaw_nees_mean: float
    sigma_xy_mean: float
    matched_share: float
    t_core_median_ms: float  # over all scans
    key_share: float  # share of key scans (motion filter)
    t_core_key_median_ms: float  # over key scans only (prediction + matching + covariance + fusion)
    t_field_mean_ms: float
    t_integrate_mean_ms: float
    # with the pose graph (``--loop-closure``; NaN / 0 without): online = each scan as corrected then,
    # optimised = after the whole run; false closures: off the truth by > 5 cm or > 1 deg
    lc_ate_rmse: float = float("nan")
    lc_ate_max: float = float("nan")
    lc_final_drift: float = float("nan")
    lc_nees_mean: float = float("nan")  # the corrected estimate's, against its covariance
    lc_inside_95: float = float("nan")
    lc_opt_ate_rmse: float = float("nan")
    lc_opt_ate_max: float = float("nan")
    lc_checks: int = 0
    lc_closures: int = 0
    lc_false_closures: int = 0
    lc_chain_unscaled: int = 0
    lc_backend_ms_mean: float = float("nan")
    lc_backend_ms_max: float = float("nan")
    gated: int = 0  # key-scan matches rejected by the gate
    lost_events: int = 0  # times the track became lost
    ambiguous_events: int = 0  # streaks of gated matches judged aliases (estimate kept on odometry)

    def as_dict(self) -> dict:
        return asdict(self)


def run_estimator(run, config: EstimatorConfig | None = None, *, causal: bool = True, glass_oracle: bool = False,
                  on_scan=None, progress: bool = False, occupancy=None, world=None, glass_online: bool = False,
                  classifier=None, backend=None, odometry_lag: float = 0.0, drop_scans: float = 0.0
                  ) -> tuple[Trajectory, PoseEstimator]:
    """Feed a :class:`glassmap.sim.dataset.SimRun` through a fresh :class:`PoseEstimator`.

    The estimator starts at the true pose of the first odometry sample (that anchors the map frame), with
    the run's laser mount. ``causal``: a scan sees only odometry stamped at or before it (as online; the
    estimator extrapolates), otherwise also the next sample (interpolation only). ``glass_oracle``: write
    the simulator's true glass cells into a ``"glass"`` layer (p = 0.95) before the run, to measure what
    glass down-weighting can give at best. ``on_scan(i, scan, estimate, estimator)`` is called after each
    update (the online glass mappers hook in here). ``occupancy``: the grid to build (default: a new one).
    ``world``: the run's world (a :class:`~glassmap.sim.world.World`, a name or a path) for the oracle
    (default: ``run.world_name``, a built-in name). ``glass_online``: build the glass map online as the
    runtime does (a :class:`~glassmap.mapping.GlassMapper` with ``classifier`` on the estimator's grid, its
    ``"glass"`` layer read by ``EstimatorConfig.glass_weighting``; every scan). ``backend``: a
    :class:`~glassmap.pose.backend.GraphBackEnd` fed every key scan (synchronously here: the front end does
    not depend on it, so the results are those of the runtime's worker). ``odometry_lag`` (s): each
    odometry message reaches the estimator this much later than its stamp (as under CPU load);
    ``drop_scans``: this share of the scans, drawn at random (generator seeded with the run's seed), never
    reaches it; the trajectory holds the scans that did (``on_scan`` gets their index in the run).
    """
    mount = tuple(run.params.get("robot", {}).get("laser_offset", (0.1, 0.0, 0.0)))
    start = np.asarray(run.odom_true_poses[0], dtype=np.float64)
    base = config if config is not None else EstimatorConfig()
    cfg = replace(base, laser_mount=tuple(float(v) for v in mount), initial_pose=tuple(float(v) for v in start))
    est = PoseEstimator(cfg, occupancy)
    if glass_oracle:
        write_glass_oracle(est, run, world)
    if glass_online:
        on_scan = _online_glass_hook(est, classifier, on_scan)
    odo = run.odometry()
    o_t = run.odom_stamps
    kept = np.arange(run.n_scans)
    if drop_scans > 0:
        kept = kept[np.random.default_rng(run.seed).random(run.n_scans) >= drop_scans]
    s = kept.size
    poses, covs = np.zeros((s, 3)), np.zeros((s, 3, 3))
    t_core, t_field, t_int = np.zeros(s), np.zeros(s), np.zeros(s)
    key = np.zeros(s, dtype=bool)
    corrected = np.zeros((s, 3)) if backend is not None else None
    corrected_covs = np.zeros((s, 3, 3)) if backend is not None else None
    latest = None  # the back end's GraphCorrection after its newest key scan
    last_key = np.zeros(s, dtype=np.int64)
    key_scan: list[int] = []
    t_back: list[float] = []
    j = 0
    it = range(s)  # positions in kept
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"{run.world_name} seed {run.seed}", unit="scan", leave=False)
    for k in it:
        i = int(kept[k])
        stamp = run.scan_stamps[i]
        limit = stamp if causal else (o_t[min(np.searchsorted(o_t, stamp), len(o_t) - 1)])
        limit -= odometry_lag
        while j < len(odo) and o_t[j] <= limit + 1e-12:
            est.predict(odo[j])
            j += 1
        scan = run.scan(i)
        e = est.update(scan)
        poses[k], covs[k] = e.pose, e.covariance
        st = est.stats
        t_core[k], t_field[k], t_int[k], key[k] = st.t_core, st.t_field, st.t_integrate, st.last_keyframe
        if backend is not None:
            if st.last_keyframe:
                t = time.perf_counter()
                backend.add(est.last_key_scan)
                t_back.append(time.perf_counter() - t)
                key_scan.append(i)
                latest = backend.latest()
            last_key[k] = len(backend) - 1
            c = corrected_estimate(e, latest, backend.config, est.off_chain_covariance())
            corrected[k], corrected_covs[k] = c.pose, c.covariance
        if on_scan is not None:
            on_scan(i, scan, e, est)
    odom_map = _odometry_in_map(run, start)[kept]
    traj = Trajectory(stamps=run.scan_stamps[kept], poses=poses, covs=covs, truth=run.scan_true_poses[kept],
                      odom=odom_map, t_core=t_core, t_field=t_field, t_integrate=t_int,
                      matched=est.stats.matched, no_match=est.stats.no_match, gated=est.stats.gated,
                      key=key, lost_events=est.stats.lost_events,
                      ambiguous_events=est.stats.ambiguous_events)
    if backend is not None:
        _add_backend(traj, backend, run, np.asarray(key_scan, dtype=np.int64), last_key, corrected, corrected_covs,
                     t_back)
    return traj, est


def _add_backend(traj: Trajectory, backend, run, key_scan: np.ndarray, last_key: np.ndarray, corrected: np.ndarray,
                 corrected_covs: np.ndarray, t_back: list[float]) -> None:
    """Fill the back end's part of ``traj``: optimised poses (every scan moved with its last key scan) and
    each closure's error against the truth."""
    opt = backend.poses()
    front = np.array([k.pose for k in backend.keys])
    traj.corrected, traj.corrected_covs = corrected, corrected_covs
    traj.optimised = np.array([compose(opt[k], relative(front[k], p)) for k, p in zip(last_key, traj.poses)])
    traj.closures = list(backend.closures)
    truth = run.scan_true_poses[key_scan]
    err = np.zeros((len(backend.closures), 2))
    for n, c in enumerate(backend.closures):  # a handful per run
        err[n] = c.error(truth[c.anchor], truth[c.node])
    traj.closure_truth_error = err
    traj.t_backend = np.asarray(t_back)
    traj.closure_checks = backend.closer.stats.checks
    traj.chain_unscaled = backend.chain_unscaled


def _odometry_in_map(run, start: np.ndarray) -> np.ndarray:
    """Raw odometry interpolated to the scan stamps, expressed in the map frame from the true start."""
    t = run.scan_stamps
    o = run.odom_poses
    o0 = o[0]
    yaw = np.unwrap(o[:, 2])
    x, y, th = (np.interp(t, run.odom_stamps, o[:, 0]), np.interp(t, run.odom_stamps, o[:, 1]),
                np.interp(t, run.odom_stamps, yaw))
    out = np.zeros((t.size, 3))
    c, s = np.cos(-o0[2]), np.sin(-o0[2])
    for k in range(t.size):  # evaluation only, not on the hot path
        rel = np.array([c * (x[k] - o0[0]) - s * (y[k] - o0[1]), s * (x[k] - o0[0]) + c * (y[k] - o0[1]),
                        th[k] - o0[2]])
        out[k] = compose(start, rel)
    return out


def _online_glass_hook(est: PoseEstimator, classifier, then):
    """An on_scan hook running the runtime's glass path (classify; register as the runtime does by default,
    robust 3x3 with visibility, with its registration sigma, the pose's uncertainty relative to the map built
    so far; update the glass map) on the estimator's grid at the estimated pose, then ``then``."""
    from glassmap.mapping import GlassMapper, MapperConfig
    from glassmap.pose.corrected import online_sigma

    if classifier is None:
        from glassmap.classifier import GlassClassifier

        classifier = GlassClassifier.load_default()
    mapper = GlassMapper(est.occupancy, MapperConfig(visibility=True), classifier=classifier)
    est.protect_mask_fn = mapper.protect_mask

    def hook(i, scan, e, estimator):
        sigma = online_sigma(estimator, e, scan.ranges, "map")
        mapper.process(scan, estimator.laser_pose(e), sigma, update_occupancy=False)
        if then is not None:
            then(i, scan, e, estimator)

    return hook


def write_glass_oracle(est: PoseEstimator, run, world=None) -> None:
    """Write the true glass cells of ``world`` (a World, a built-in name or a world file; default
    ``run.world_name``) into the estimator grid's ``"glass"`` layer (p = 0.95)."""
    from glassmap.sim.blueprint import Blueprint
    from glassmap.sim.world import World, load_world

    world = world if isinstance(world, World) else load_world(world if world is not None else run.world_name)
    bp = Blueprint.from_world(world, resolution=est.occupancy.grid.resolution)
    g = est.occupancy.grid
    lo, hi = bp.origin, bp.origin + np.array(bp.labels.shape[::-1]) * bp.resolution
    g.ensure_contains(lo - 1.0, hi + 1.0)
    if "glass" not in g.layer_names:
        g.add_layer("glass", 0.0, np.float32)
    iy, ix = np.nonzero(bp.labels == 2)
    xy = bp.origin + (np.stack([ix, iy], axis=1) + 0.5) * bp.resolution
    cells = g.world_to_cell(xy)
    g["glass"][cells[:, 1], cells[:, 0]] = np.float32(np.log(0.95 / 0.05))


def _nees(err: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """(S,) squared Mahalanobis distances of errors (S, 3) under covariances (S, 3, 3)."""
    return np.einsum("si,si->s", err, np.linalg.solve(covs, err[:, :, None])[:, :, 0])


def axis_nees(err: np.ndarray, covs: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(S, 3) squared errors over their variances per axis alone: position along and across ``heading`` (S,)
    rad, and yaw; errors (S, 3) and covariances (S, 3, 3) in the map frame (x, y, yaw)."""
    u = np.stack([np.cos(heading), np.sin(heading)], axis=1)  # along the track
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)  # across it
    out = np.empty((err.shape[0], 3))
    for j, v in enumerate((u, n)):
        out[:, j] = np.einsum("si,si->s", err[:, :2], v) ** 2 / np.einsum("si,sij,sj->s", v, covs[:, :2, :2], v)
    out[:, 2] = err[:, 2] ** 2 / covs[:, 2, 2]
    return out


def _mean_or_nan(a: np.ndarray) -> float:
    return float(a.mean()) if a.size else float("nan")


def metrics(traj: Trajectory, run) -> RunMetrics:
    """Trajectory and consistency metrics of one run."""
    e = traj.poses - traj.truth
    e[:, 2] = wrap_angle(e[:, 2])
    d = np.hypot(e[:, 0], e[:, 1])
    eo = traj.odom - traj.truth
    do = np.hypot(eo[:, 0], eo[:, 1])
    nees = _nees(e, traj.covs)
    axes = axis_nees(e, traj.covs, traj.truth[:, 2])
    yaw_nees = axes[:, 2]
    steps = np.diff(traj.truth[:, :2], axis=0)
    sig = np.sqrt(np.linalg.eigvalsh(traj.covs[:, :2, :2])[:, 1])
    s = len(traj.stamps)
    lc = {}
    if traj.corrected is not None:
        ec = traj.corrected - traj.truth
        ec[:, 2] = wrap_angle(ec[:, 2])
        dc = np.hypot(ec[:, 0], ec[:, 1])
        nees_c = _nees(ec, traj.corrected_covs)
        dopt = np.hypot(*(traj.optimised[:, :2] - traj.truth[:, :2]).T)
        ce = traj.closure_truth_error
        tb = traj.t_backend if traj.t_backend is not None and traj.t_backend.size else np.zeros(1)
        lc = dict(lc_ate_rmse=float(np.sqrt(np.mean(dc ** 2))), lc_ate_max=float(dc.max()), lc_final_drift=float(dc[-1]),
                  lc_nees_mean=float(nees_c.mean()), lc_inside_95=float(np.mean(nees_c <= CHI2_3DOF_95)),
                  lc_opt_ate_rmse=float(np.sqrt(np.mean(dopt ** 2))), lc_opt_ate_max=float(dopt.max()),
                  lc_checks=int(traj.closure_checks), lc_closures=len(traj.closures),
                  lc_false_closures=int(np.sum((ce[:, 0] > FALSE_CLOSURE_XY) | (ce[:, 1] > FALSE_CLOSURE_YAW))),
                  lc_chain_unscaled=int(traj.chain_unscaled),
                  lc_backend_ms_mean=float(tb.mean() * 1e3), lc_backend_ms_max=float(tb.max() * 1e3))
    return RunMetrics(
        world=run.world_name, route=run.route_name, seed=int(run.seed), scans=s,
        length_m=float(np.hypot(steps[:, 0], steps[:, 1]).sum()),
        ate_rmse=float(np.sqrt(np.mean(d ** 2))), ate_max=float(d.max()), final_drift=float(d[-1]),
        yaw_rmse_deg=float(np.degrees(np.sqrt(np.mean(e[:, 2] ** 2)))),
        odom_ate_rmse=float(np.sqrt(np.mean(do ** 2))), odom_ate_max=float(do.max()), odom_final_drift=float(do[-1]),
        nees_mean=float(nees.mean()), nees_median=float(np.median(nees)),
        inside_95=float(np.mean(nees <= CHI2_3DOF_95)),
        nees_key_mean=_mean_or_nan(nees[traj.key]), nees_between_mean=_mean_or_nan(nees[~traj.key]),
        yaw_nees_key_mean=_mean_or_nan(yaw_nees[traj.key]), yaw_nees_between_mean=_mean_or_nan(yaw_nees[~traj.key]),
        along_nees_mean=float(axes[:, 0].mean()), cross_nees_mean=float(axes[:, 1].mean()),
        yaw_nees_mean=float(axes[:, 2].mean()),
        sigma_xy_mean=float(sig.mean()),
        matched_share=float(traj.matched / max(s, 1)),
        t_core_median_ms=float(np.median(traj.t_core) * 1e3),
        key_share=float(traj.key.mean()) if s else 0.0,
        t_core_key_median_ms=float(np.median(traj.t_core[traj.key]) * 1e3) if traj.key.any() else 0.0,
        t_field_mean_ms=float(np.mean(traj.t_field) * 1e3),
        t_integrate_mean_ms=float(np.mean(traj.t_integrate) * 1e3), gated=int(traj.gated),
        lost_events=int(traj.lost_events),
        ambiguous_events=int(traj.ambiguous_events), **lc)


def evaluate_run(world: str, route: str | None, seed: int, config: EstimatorConfig | None = None, *,
                 causal: bool = True, glass_oracle: bool = False, progress: bool = False,
                 run_cache: dict | None = None, sweep_motion: bool = False, glass_online: bool = False,
                 classifier=None, backend_config=None, odometry_lag: float = 0.0,
                 drop_scans: float = 0.0) -> RunMetrics:
    """Simulate (or take from ``run_cache``) one run and evaluate the estimator on it. ``sweep_motion``: the
    simulated laser takes each beam from where it is when the beam fires (see ``simulate_run``);
    ``odometry_lag``, ``drop_scans``: see :func:`run_estimator`. ``backend_config``: also run the pose-graph
    back end (:class:`~glassmap.pose.backend.BackEndConfig`)."""
    from glassmap.sim.dataset import simulate_run

    key = (world, route, seed, sweep_motion)
    run = run_cache.get(key) if run_cache is not None else None
    if run is None:
        run = simulate_run(world, route, seed=seed, sweep_motion=sweep_motion)
        if run_cache is not None:
            run_cache[key] = run
    backend = None
    if backend_config is not None:
        from glassmap.pose.backend import GraphBackEnd

        backend = GraphBackEnd(backend_config, (config or EstimatorConfig()).likelihood.sigma_hit)
    traj, _ = run_estimator(run, config, causal=causal, glass_oracle=glass_oracle, progress=progress, world=world,
                            glass_online=glass_online, classifier=classifier, backend=backend,
                            odometry_lag=odometry_lag, drop_scans=drop_scans)
    return metrics(traj, run)
