"""One trial of the paper's experiment (docs/method.md section 6).

The simulated robot drives a route through a world; scans are simulated at ``scan_rate``. The estimated laser
pose is the true pose plus an error from :class:`~glassmap.eval.pose_error.PoseErrorModel`. One occupancy
grid is built (shared by all methods, as one SLAM run feeds all of them in the paper); the classifier runs
once per scan; every method then registers the same beams into its own glass layer at the estimated pose,
with the sigma of the error model. Methods that change the occupancy update (``*-protect``) get their own
occupancy grid. ``TrialConfig.map_poses`` says which poses build the occupancy grid: ``"truth"`` (default:
a consistent map, as a SLAM back end provides, with only the robot's pose against it uncertain, the
situation robust registration is designed for) or ``"estimate"`` (the same noisy poses as the
registration, so that the pose error also smears the walls of the occupancy grid).

Scoring: blueprint wall/glass cells that (a) were seen by at least one returned beam (true end points from
the true poses) and (b) lie within ``eval_radius`` of a glass cell (the "areas that
have both walls and glass"). A cell counts as correct when its map label agrees with the blueprint; not
occupied, undecided (|p - 0.5| <= GlassParams.undecided) or never registered counts as an error.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..grid import MapGrid, OccupancyGrid, OccupancyParams
from ..mapping import GlassMapper, MapperConfig
from ..types import Scan
from .metrics import MapScore, score_map
from .pose_error import PoseErrorModel

METHODS: dict[str, dict] = {
    "direct": dict(registration="direct"),
    "robust3": dict(registration="robust", window=3),
    "robust5": dict(registration="robust", window=5),
    "robust3-endpoint": dict(registration="robust", window=3, decay_ref="endpoint"),
    "robust5-endpoint": dict(registration="robust", window=5, decay_ref="endpoint"),
    "direct-beam": dict(registration="direct", aggregation="beam"),
    "robust3-beam": dict(registration="robust", window=3, aggregation="beam"),
    "robust5-beam": dict(registration="robust", window=5, aggregation="beam"),
    "robust3-protect-glass": dict(registration="robust", window=3, protect="glass"),
    "robust3-no-protect": dict(registration="robust", window=3, protect="none"),
    "robust3-plain": dict(registration="robust", window=3, protect="none", glass_hits_occupy=False),
    "robust3-vis": dict(registration="robust", window=3, visibility=True),
    "robust5-vis": dict(registration="robust", window=5, visibility=True),
}
"""Method name -> MapperConfig fields. ``-beam``: per-beam update (the paper); default per-scan mean.
``-endpoint``: eq. 6 distance from the beam end point; default from c_hat_j. The default occupancy update
(shared by the methods that use it) restores cells hit by glass-classified beams and protects them from
clearing; ``-protect-glass`` protects the cells the method's glass map believes are glass instead,
``-no-protect`` does not protect, ``-plain`` neither restores nor protects (each with its own occupancy grid)."""

MAP_POSES: tuple[str, ...] = ("truth", "estimate")

DEFAULT_METHODS: tuple[str, ...] = ("direct", "robust3", "robust5", "robust3-endpoint", "direct-beam",
                                    "robust3-beam")


@dataclass(frozen=True)
class TrialConfig:
    """Settings of one trial.

    world / route: built-in world name or path, route name (None = the world's default route).
    duration: stop after this many seconds of driving (None = drive the whole route).
    scan_rate: scans per second that are simulated and mapped (Hz). sigma_mode: registration sigma per beam
    ("beam": sqrt(sigma_xy^2 + (r sigma_theta)^2)) or the position sigma only ("xy").
    eval_radius: m around glass cells that define the evaluated area. resolution: grid cell (m).
    max_free_range: how far (m) a beam clears free space in the occupancy update (OccupancyParams; 10 m
    instead of the default 20 m keeps trials fast: the ray casting cost grows with the longest beam).
    map_poses: poses the occupancy grid is built from, "truth" or "estimate" (see the module docstring).
    """

    world: str = "office"
    route: str | None = None
    duration: float | None = None
    scan_rate: float = 10.0
    pose_error: PoseErrorModel = field(default_factory=PoseErrorModel)
    sigma_mode: str = "beam"
    methods: tuple[str, ...] = DEFAULT_METHODS
    eval_radius: float = 1.5
    resolution: float = 0.05
    angle_method: str = "split-merge"
    weights: str | None = None
    max_v: float = 0.5
    max_free_range: float = 10.0
    map_poses: str = "truth"

    def __post_init__(self) -> None:
        if self.map_poses not in MAP_POSES:
            raise ValueError(f"map_poses must be one of {', '.join(MAP_POSES)}, got {self.map_poses!r}")
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise ValueError(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
        if self.sigma_mode not in ("beam", "xy"):
            raise ValueError(f"sigma_mode must be 'beam' or 'xy', got {self.sigma_mode!r}")
        if self.scan_rate <= 0 or self.scan_rate > 40:
            raise ValueError(f"scan_rate must be in (0, 40] Hz, got {self.scan_rate}")


@dataclass
class TrialResult:
    seed: int
    scores: dict[str, MapScore]
    n_scans: int
    seconds: float
    sim_seconds: float
    config: dict

    def rows(self, trial: int) -> list[dict]:
        pe = self.config["pose_error"]
        return [dict(trial=trial, seed=self.seed, world=self.config["world"], sigma_xy=pe["sigma_xy"],
                     sigma_theta=pe["sigma_theta"], tau=pe["tau"], method=m, n_scans=self.n_scans,
                     **asdict(s)) for m, s in self.scores.items()]


def drive(world, cfg: TrialConfig, rng: np.random.Generator):
    """Drive the route; returns (stamps (k,), true laser poses (k, 3), list of SimScan)."""
    from ..sim.laser import simulate_scan
    from ..sim.robot import DiffDriveRobot, RobotParams, RouteFollower

    wp = world.route(cfg.route)
    d0 = wp[1] - wp[0]
    robot_rng, laser_rng = (np.random.default_rng(s) for s in rng.bit_generator.seed_seq.spawn(2))
    robot = DiffDriveRobot(RobotParams(), pose0=(wp[0][0], wp[0][1], math.atan2(d0[1], d0[0])), rng=robot_rng)
    follower = RouteFollower(wp, max_v=cfg.max_v)
    dt = 0.025
    every = max(1, int(round(1.0 / (cfg.scan_rate * dt))))
    limit = cfg.duration if cfg.duration is not None else 900.0
    stamps, poses, scans = [], [], []
    step = 0
    while not follower.done and step * dt < limit:
        v, w = follower.command(robot.true_pose)
        robot.set_velocity(v, w)
        robot.step(dt)
        step += 1
        if step % every == 0:
            lp = robot.laser_pose()
            stamps.append(step * dt)
            poses.append(lp)
            scans.append(simulate_scan(world, lp, laser_rng))
    return np.array(stamps), np.array(poses).reshape(-1, 3), scans


def evaluation_mask(blueprint_labels: np.ndarray, seen: np.ndarray, resolution: float, radius: float) -> np.ndarray:
    """Wall/glass cells that were seen and lie within ``radius`` m of a glass cell."""
    from scipy import ndimage

    glass = blueprint_labels == 2
    if not glass.any():
        return np.zeros_like(glass)
    near = ndimage.distance_transform_edt(~glass) * resolution <= radius
    return near & seen & (blueprint_labels > 0)


def run_trial(cfg: TrialConfig, seed: int, classifier=None) -> TrialResult:
    """Simulate, map with every method of ``cfg.methods`` on the same data, and score against the blueprint."""
    from ..classifier import GlassClassifier
    from ..sim.blueprint import Blueprint
    from ..sim.world import load_world

    t0 = time.perf_counter()
    world = load_world(cfg.world)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    stamps, true_poses, sims = drive(world, cfg, rng)
    t_sim = time.perf_counter() - t0
    errors = cfg.pose_error.sample(stamps, rng)
    est = true_poses + errors
    map_poses = true_poses if cfg.map_poses == "truth" else est

    bp = Blueprint.from_world(world, resolution=cfg.resolution)
    if classifier is None:
        classifier = GlassClassifier.load(cfg.weights) if cfg.weights else GlassClassifier.load_default()
    occ_params = OccupancyParams(max_free_range=cfg.max_free_range)
    shared = OccupancyGrid(MapGrid(cfg.resolution, origin=tuple(bp.origin), shape=bp.labels.shape, grow_step_m=5.0),
                           occ_params)
    mappers: dict[str, GlassMapper] = {}
    own: dict[str, GlassMapper] = {}
    for m in cfg.methods:
        mc = MapperConfig(angle_method=cfg.angle_method, layer=f"glass_{m}", **METHODS[m])
        if mc.protect != "hits" or not mc.glass_hits_occupy:
            occ = OccupancyGrid(MapGrid(cfg.resolution, origin=tuple(bp.origin), shape=bp.labels.shape,
                                        grow_step_m=5.0), occ_params)
            own[m] = GlassMapper(occ, mc, classifier=classifier)
        else:
            mappers[m] = GlassMapper(shared, mc, classifier=classifier)
    first = next(iter(mappers.values()), None)
    seen = np.zeros(bp.labels.shape, dtype=bool)
    h, w = bp.labels.shape
    for k, s in enumerate(sims):
        scan = Scan(stamp=float(stamps[k]), ranges=s.ranges, intensities=s.intensities, geometry=s.geometry, seq=k)
        pose = est[k]
        if cfg.sigma_mode == "beam":
            sigma = cfg.pose_error.beam_sigma(s.ranges)
        else:
            sigma = np.full(s.ranges.shape, cfg.pose_error.sigma_xy)
        # truth: which blueprint cells were seen (returned beams, true end points)
        ret = np.isfinite(s.ranges) & np.isfinite(s.true_range)
        ang = true_poses[k, 2] + s.geometry.angles[ret]
        # rounded to 1 um so that points on walls lying on cell boundaries fall where the blueprint put them
        ex = np.round(true_poses[k, 0] + s.true_range[ret] * np.cos(ang), 6)
        ey = np.round(true_poses[k, 1] + s.true_range[ret] * np.sin(ang), 6)
        cx = np.floor((ex - bp.origin[0]) / bp.resolution).astype(np.int64)
        cy = np.floor((ey - bp.origin[1]) / bp.resolution).astype(np.int64)
        ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        seen[cy[ok], cx[ok]] = True
        if first is not None:
            beams, use = first.classify(scan)
            first.integrate(scan, map_poses[k])
            first.mark_glass_hits(beams, use, scan, map_poses[k])
            use &= np.isfinite(sigma)
            for mp in mappers.values():
                mp.register(beams, use, scan, pose, sigma)
        for mp in own.values():
            mp.process(scan, pose, sigma, occupancy_pose=map_poses[k])

    mask = evaluation_mask(bp.labels, seen, bp.resolution, cfg.eval_radius)
    scores = {}
    for m in cfg.methods:
        mp = mappers.get(m) or own[m]
        lab = mp.glass.labels(mp.occupancy)
        off = np.rint((bp.origin - mp.grid.origin) / bp.resolution).astype(int)
        sub = lab[off[1]:off[1] + h, off[0]:off[0] + w]
        scores[m] = score_map(sub, bp.labels, mask)
    cdict = asdict(cfg)
    return TrialResult(seed=seed, scores=scores, n_scans=len(sims), seconds=time.perf_counter() - t0,
                       sim_seconds=t_sim, config=cdict)


def build_maps_for_export(cfg: TrialConfig, seed: int, method: str = "robust3", classifier=None):
    """Drive one trial and return the mapper of ``method`` (for PNG / PGM export and inspection)."""
    res_cfg = replace(cfg, methods=(method,))
    from ..classifier import GlassClassifier
    from ..sim.world import load_world

    world = load_world(res_cfg.world)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    stamps, true_poses, sims = drive(world, res_cfg, rng)
    est = true_poses + res_cfg.pose_error.sample(stamps, rng)
    map_poses = true_poses if res_cfg.map_poses == "truth" else est
    if classifier is None:
        classifier = GlassClassifier.load(cfg.weights) if cfg.weights else GlassClassifier.load_default()
    mapper = GlassMapper(None, MapperConfig(angle_method=cfg.angle_method, **METHODS[method]), classifier=classifier)
    for k, s in enumerate(sims):
        scan = Scan(stamp=float(stamps[k]), ranges=s.ranges, intensities=s.intensities, geometry=s.geometry, seq=k)
        sigma = (res_cfg.pose_error.beam_sigma(s.ranges) if res_cfg.sigma_mode == "beam"
                 else res_cfg.pose_error.sigma_xy)
        mapper.process(scan, est[k], sigma, occupancy_pose=map_poses[k])
    return mapper
