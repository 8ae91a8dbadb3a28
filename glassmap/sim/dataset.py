"""Simulated runs: drive a route through a world and record scans, odometry, true poses and per-beam labels.

A ``SimRun`` holds everything as arrays (one row per scan / per odometry sample) and saves to / loads from a
single ``.npz`` file. Times are simulated seconds from the start of the run. Frames: true poses and laser poses
in ``map``, odometry in ``odom`` (origin = the robot's start pose), ranges in ``laser``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from glassmap.sim.laser import LaserParams, simulate_scan, world_laser_params
from glassmap.sim.robot import DiffDriveRobot, OdometryNoise, RobotParams, RouteFollower, compose
from glassmap.sim.world import World, load_world
from glassmap.types import LaserGeometry, Odometry, Scan

FORMAT_VERSION = 1


class DatasetError(ValueError):
    """A dataset file is missing, unreadable or not a glassmap simulator run."""


@dataclass
class SimRun:
    """A recorded simulated run.

    Scans (S rows, n beams): ``scan_stamps`` (S,) s; ``laser_poses`` / ``scan_true_poses`` (S, 3) true laser /
    base pose in the map frame; ``ranges``, ``intensities`` (S, n) measurements (NaN invalid, +inf no return);
    truth per beam ``true_range``, ``material`` (MaterialKind code, -1 nothing), ``incidence`` (rad, NaN
    none), ``is_glass``, ``crossed_glass``, ``segment`` (world segment index, -1 none); multi-echo
    ``last_echo_range``, ``last_echo_intensity`` (S, n) (NaN / 0 where a beam had one echo) or None;
    ``is_ghost`` (S, n) the first echo is a mirror image (None in files written before mirror reflections).
    Odometry (O rows): ``odom_stamps`` (O,) s, ``odom_poses`` (O, 3) odom frame, ``odom_velocities`` (O, 2)
    measured (v, omega), ``wheel_speeds`` (O, 2) measured (left, right) m/s, ``odom_true_poses`` (O, 3) map.
    ``params``: the laser, robot and odometry-noise parameters used (JSON-able dict).
    """

    world_name: str
    route_name: str
    seed: int
    route: np.ndarray
    geometry: LaserGeometry
    scan_stamps: np.ndarray
    laser_poses: np.ndarray
    scan_true_poses: np.ndarray
    ranges: np.ndarray
    intensities: np.ndarray
    true_range: np.ndarray
    material: np.ndarray
    incidence: np.ndarray
    is_glass: np.ndarray
    crossed_glass: np.ndarray
    segment: np.ndarray
    odom_stamps: np.ndarray
    odom_poses: np.ndarray
    odom_velocities: np.ndarray
    wheel_speeds: np.ndarray
    odom_true_poses: np.ndarray
    last_echo_range: np.ndarray | None = None
    last_echo_intensity: np.ndarray | None = None
    is_ghost: np.ndarray | None = None
    params: dict = field(default_factory=dict)

    @property
    def n_scans(self) -> int:
        return int(self.scan_stamps.shape[0])

    @property
    def duration(self) -> float:
        """Simulated duration (s)."""
        return float(self.scan_stamps[-1] - self.scan_stamps[0]) if self.n_scans else 0.0

    def scan(self, i: int) -> Scan:
        """Scan i as a ``glassmap.types.Scan`` (echoes = [first, last] when multi-echo was recorded)."""
        echoes = echo_i = None
        if self.last_echo_range is not None:
            echoes = np.stack([self.ranges[i], self.last_echo_range[i]], axis=1).astype(np.float64)
            echo_i = np.stack([self.intensities[i], self.last_echo_intensity[i]], axis=1).astype(np.float64)
        return Scan(stamp=float(self.scan_stamps[i]), ranges=self.ranges[i], intensities=self.intensities[i],
                    geometry=self.geometry, seq=i, echoes=echoes, echo_intensities=echo_i)

    def scans(self) -> Iterator[Scan]:
        for i in range(self.n_scans):
            yield self.scan(i)

    def odometry(self) -> list[Odometry]:
        """The odometry samples as ``glassmap.types.Odometry`` (covariance left at zero: not modelled here)."""
        return [Odometry(stamp=float(t), x=float(p[0]), y=float(p[1]), yaw=float(p[2]), v=float(v[0]),
                         omega=float(v[1]))
                for t, p, v in zip(self.odom_stamps, self.odom_poses, self.odom_velocities)]

    # ------------------------------------------------------------------------------------------ files
    def save(self, path: str | Path, compress: bool = True) -> Path:
        """Write the run to ``path`` (.npz; the suffix is added if missing). Returns the path written."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = dict(format="glassmap-simrun", version=FORMAT_VERSION, world_name=self.world_name,
                    route_name=self.route_name, seed=self.seed, geometry=dataclasses.asdict(self.geometry),
                    params=self.params)
        arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                  if isinstance(getattr(self, f.name), np.ndarray)}
        (np.savez_compressed if compress else np.savez)(path, meta=np.array(json.dumps(meta)), **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "SimRun":
        """Read a run written by ``save``. Raises DatasetError with the file and the problem."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise DatasetError(f"{path}: cannot read simulator dataset: {e}") from e
        if "meta" not in data:
            raise DatasetError(f"{path}: not a glassmap simulator dataset (no 'meta' entry)")
        meta = json.loads(str(data.pop("meta")))
        if meta.get("format") != "glassmap-simrun" or meta.get("version") != FORMAT_VERSION:
            raise DatasetError(f"{path}: unsupported dataset format {meta.get('format')!r} "
                               f"version {meta.get('version')!r} (expected glassmap-simrun {FORMAT_VERSION})")
        names = {f.name for f in dataclasses.fields(cls)}
        missing = sorted(n for n in names - set(data) - {"world_name", "route_name", "seed", "geometry", "params",
                                                          "last_echo_range", "last_echo_intensity", "is_ghost"})
        if missing:
            raise DatasetError(f"{path}: dataset is missing arrays {missing}")
        return cls(world_name=meta["world_name"], route_name=meta["route_name"], seed=int(meta["seed"]),
                   geometry=LaserGeometry(**meta["geometry"]), params=meta["params"],
                   **{k: v for k, v in data.items() if k in names})


def _params_dict(obj: object) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(obj).items()}


def _sweep_end_pose(robot: DiffDriveRobot, geometry: LaserGeometry) -> np.ndarray:
    """Laser pose (map frame) when the last beam of a scan started now is taken: the base moves on with
    its current true velocity (an arc) for the sweep time, (n - 1) * time_increment."""
    sweep = geometry.time_increment * (geometry.n_beams - 1)
    v, om = robot.velocity
    half = 0.5 * om * sweep
    delta = np.array([v * sweep * math.cos(half), v * sweep * math.sin(half), om * sweep])
    return compose(compose(robot.true_pose, delta), np.asarray(robot.params.laser_offset, dtype=np.float64))


def simulate_run(world: World | str, route: str | np.ndarray | None = None, seed: int = 0, *,
                 laser_params: LaserParams | None = None, geometry: LaserGeometry = LaserGeometry(),
                 robot_params: RobotParams = RobotParams(), odom_noise: OdometryNoise = OdometryNoise(),
                 scan_rate: float = 40.0, odom_rate: float = 10.0, max_v: float = 0.5,
                 max_omega: float = math.radians(60), max_duration: float = 600.0,
                 sweep_motion: bool = False, progress: bool = False) -> SimRun:
    """Drive ``route`` (a route name of the world, waypoints (k, 2) in the map frame, or None = the world's
    default route) from the route's first waypoint (``laser_params`` None: the world's, see
    ``world_laser_params``), heading along its first leg; record scans at
    ``scan_rate`` Hz and odometry at ``odom_rate`` Hz until the robot has stopped at the last waypoint.

    The route follower steers on the true pose (the simulated robot drives where the route says). The same
    ``seed`` gives the same run; the robot's slip noise and the laser noise use independent streams.
    ``sweep_motion``: each beam is taken from where the laser is when it fires (the robot keeps moving with
    its current velocity during the ~19 ms sweep; ``laser_poses`` are then the poses at the first beam);
    default off: all beams of a scan from one pose.
    Raises ValueError if the rates do not divide or the route is not finished within ``max_duration`` s.
    """
    w = load_world(world) if isinstance(world, str) else world
    laser_params = laser_params if laser_params is not None else world_laser_params(w)
    if isinstance(route, str) or route is None:
        route_name = route if route is not None else (w.default_route or "")
        waypoints = w.route(route)
    else:
        route_name = "custom"
        waypoints = np.asarray(route, dtype=np.float64)
    ratio = scan_rate / odom_rate
    if scan_rate <= 0 or odom_rate <= 0 or abs(ratio - round(ratio)) > 1e-9:
        raise ValueError(f"scan_rate ({scan_rate} Hz) must be a positive multiple of odom_rate ({odom_rate} Hz)")
    every = int(round(ratio))
    dt = 1.0 / scan_rate
    ss = np.random.SeedSequence(seed)
    robot_rng, laser_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    d0 = waypoints[1] - waypoints[0]
    robot = DiffDriveRobot(robot_params, odom_noise, pose0=(waypoints[0][0], waypoints[0][1],
                                                            math.atan2(d0[1], d0[0])), rng=robot_rng)
    follower = RouteFollower(waypoints, max_v=max_v, max_omega=max_omega)
    n = geometry.n_beams
    cols: dict[str, list] = {k: [] for k in ("scan_stamps", "laser_poses", "scan_true_poses", "odom_stamps",
                                             "odom_poses", "odom_velocities", "wheel_speeds", "odom_true_poses")}
    n_max = int(max_duration * scan_rate) + 1
    big = dict(ranges=np.float32, intensities=np.float32, true_range=np.float32, material=np.int8,
               incidence=np.float32, is_glass=bool, crossed_glass=bool, segment=np.int32, is_ghost=bool)
    if laser_params.multi_echo:
        big.update(last_echo_range=np.float32, last_echo_intensity=np.float32)
    blocks: dict[str, list[np.ndarray]] = {k: [] for k in big}
    chunk = 400
    buf = {k: np.empty((chunk, n), dtype=t) for k, t in big.items()}
    fill = 0

    route_len = float(np.hypot(*np.diff(waypoints, axis=0).T).sum())
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=round(route_len, 1), unit=" m", desc=f"sim {w.name} (route metres)", leave=True)
    k = 0
    last_dist = 0.0
    while True:
        t = k * dt
        if k % every == 0:
            cols["odom_stamps"].append(t)
            cols["odom_poses"].append(robot.odom_pose)
            cols["odom_velocities"].append(robot.odom_velocity)
            cols["wheel_speeds"].append(robot.wheel_speeds)
            cols["odom_true_poses"].append(robot.true_pose)
        lp = robot.laser_pose()
        end = _sweep_end_pose(robot, geometry) if sweep_motion else None
        s = simulate_scan(w, lp, laser_rng, laser_params, geometry, end_pose=end)
        cols["scan_stamps"].append(t)
        cols["laser_poses"].append(lp)
        cols["scan_true_poses"].append(robot.true_pose)
        row = dict(ranges=s.ranges, intensities=s.intensities, true_range=s.true_range, material=s.material,
                   incidence=s.incidence, is_glass=s.is_glass, crossed_glass=s.crossed_glass, segment=s.segment,
                   is_ghost=s.is_ghost)
        if laser_params.multi_echo:
            row.update(last_echo_range=s.echo_ranges[:, 1], last_echo_intensity=s.echo_intensities[:, 1])
        for key, val in row.items():
            buf[key][fill] = val
        fill += 1
        if fill == chunk:
            for key in big:
                blocks[key].append(buf[key].copy())
            fill = 0
        v, om = robot.velocity
        if follower.done and abs(v) < 1e-3 and abs(om) < 1e-3:
            break
        k += 1
        if k >= n_max:
            if bar is not None:
                bar.close()
            raise ValueError(f"route {route_name!r} of world {w.name!r} not finished within {max_duration} s "
                             f"(stuck near {robot.true_pose.round(2).tolist()})")
        robot.set_velocity(*follower.command(robot.true_pose))
        robot.step(dt)
        if bar is not None and robot.distance - last_dist >= 0.5:
            bar.update(round(min(robot.distance, route_len) - last_dist, 1))
            last_dist = min(robot.distance, route_len)
    if bar is not None:
        bar.update(max(0.0, round(route_len - last_dist, 1)))
        bar.close()
    for key in big:
        blocks[key].append(buf[key][:fill].copy())
    arrays = {key: np.concatenate(blocks[key], axis=0) for key in big}
    params = dict(laser=_params_dict(laser_params), robot=_params_dict(robot_params),
                  odometry_noise=_params_dict(odom_noise), scan_rate=scan_rate, odom_rate=odom_rate,
                  max_v=max_v, max_omega=max_omega, sweep_motion=sweep_motion)
    return SimRun(world_name=w.name, route_name=route_name, seed=int(seed), route=waypoints, geometry=geometry,
                  scan_stamps=np.array(cols["scan_stamps"]), laser_poses=np.array(cols["laser_poses"]),
                  scan_true_poses=np.array(cols["scan_true_poses"]), odom_stamps=np.array(cols["odom_stamps"]),
                  odom_poses=np.array(cols["odom_poses"]), odom_velocities=np.array(cols["odom_velocities"]),
                  wheel_speeds=np.array(cols["wheel_speeds"]), odom_true_poses=np.array(cols["odom_true_poses"]),
                  params=params, **arrays)
