"""``glassmap demo``: the full runtime against emulated hardware in a simulated world.

The simulator's robot (``DiffDriveRobot``, with odometry error) sits inside the emulated Pioneer, which
serves the ARIA protocol on a pseudo-terminal; the emulated Hokuyo serves SCIP on loopback TCP and ranges
the simulated world from the robot's true laser pose. The runtime connects to both exactly as to hardware,
drives the robot along the world's route with velocity commands computed from its *estimated* pose, builds
the maps online, records everything to MCAP, and at the end the glass confidence map is scored against the
world's blueprint (with ``mapping.loop_closure``, every accepted loop closure is scored against the true
poses too and listed in ``closures.csv``). ``speed`` > 1 runs the emulators (and so the whole demo) faster
than real time; the processing queue then holds ``speed`` times as many scans (``pipeline.queue_size`` is a
number of scans at the laser's real rate, 40 Hz: 8 scans = 200 ms), so that it spans the same time as on the
robot.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from glassmap.types import PoseEstimate
from runtime.app import Runtime, RunSummary
from runtime.config import RuntimeConfig
from runtime.evaluate import (GraphEvaluation, MapEvaluation, TrajectoryEvaluation, evaluate_graph, evaluate_map,
                              evaluate_trajectory)

log = logging.getLogger(__name__)

CLOSURES_FILE = "closures.csv"  # with loop closure: every accepted closure scored against the truth


@dataclass
class DemoOptions:
    """Settings of one demo run. duration: emulated seconds (None = until the route is done)."""

    world: str = "office"
    route: str | None = None
    speed: float = 1.0
    duration: float | None = None
    out_dir: str = "out/demo"
    record: bool = True
    seed: int = 0
    max_v: float = 0.5
    max_omega: float = math.radians(60)
    registration: str | None = None  # None: keep config.mapping's
    window: int | None = None
    progress: bool = True
    laser_link_loss_at: float | None = None  # emulated s after the first scan: pull the laser cable once (tests)
    config: RuntimeConfig | None = None  # base settings (from --config and flags); demo fields override


@dataclass
class DemoResult:
    """What a demo did. true_final_pose and estimated_final_pose are of the same instant: the last processed
    scan (the true pose the emulated laser ranged from, and the estimate made from that scan);
    true_pose_at_stop is the simulator's pose when the devices stopped (after braking); trajectory scores
    every processed scan against its true pose."""

    summary: RunSummary
    evaluation: MapEvaluation | None
    png: str = ""
    recording: str = ""
    true_final_pose: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    estimated_final_pose: np.ndarray | None = None
    true_pose_at_stop: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    trajectory: TrajectoryEvaluation | None = None
    estimated_final_cov: np.ndarray | None = None  # its reported 3x3 covariance (m^2, rad^2)
    corrected_final: PoseEstimate | None = None  # with loop closure: the same estimate corrected by the pose graph
    closures: int = 0  # loop closures the pose graph had accepted by then
    graph_lag: int = 0  # key scans the pose graph had not yet taken in when that estimate was corrected
    graph: GraphEvaluation | None = None  # with loop closure: the final optimised key scans and closures scored
    corrected_evaluation: MapEvaluation | None = None  # with loop closure: the maps rebuilt at the final graph
    route_done: bool = False
    latency: list[float] = field(default_factory=list)
    stages: dict[str, list[float]] = field(default_factory=dict)
    device_report: dict = field(default_factory=dict)


def route_driver(waypoints: np.ndarray, speed: float, max_v: float, max_omega: float, progress=None):
    """A runtime driver following ``waypoints`` (map frame) from the runtime's estimated pose."""
    from drivers.errors import DriverError
    from glassmap.sim.robot import RouteFollower

    follower = RouteFollower(waypoints, max_v=max_v, max_omega=max_omega)
    legs = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    total = float(legs.sum())

    async def drive(rt: Runtime) -> None:
        period = 0.1 / speed  # 10 Hz in emulated time
        while not follower.done:
            pose = rt.pose
            if pose is None:
                await asyncio.sleep(period)
                continue
            v, w = follower.command(pose.pose)
            try:
                await rt.command_velocity(v, w)
            except DriverError as exc:  # reconnecting: the client refuses commands until the link is back
                log.info("drive: command not sent (%s)", exc)
            if progress is not None:
                done = float(legs[: follower.leg].sum())
                a = waypoints[follower.leg]
                done += min(float(np.hypot(*(pose.pose[:2] - a))), float(legs[min(follower.leg, len(legs) - 1)]))
                progress(min(done, total), total)
            await asyncio.sleep(period)
        with contextlib.suppress(DriverError):
            await rt.command_velocity(0.0, 0.0)
        await _come_to_rest(rt, speed)

    drive.follower = follower  # type: ignore[attr-defined]
    return drive


async def _come_to_rest(rt: Runtime, speed: float, timeout: float = 3.0) -> None:
    """After the last command: wait (at most ``timeout`` emulated s) until the odometry says the robot is at
    rest, then for two more processed scans, so that the final estimate is of the robot where it stopped."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout / speed
    while loop.time() < end:
        odom = rt.latest_odom
        if odom is not None and abs(odom.v) < 1e-3 and abs(odom.omega) < 1e-3:
            break
        await asyncio.sleep(0.02 / speed)
    for _ in range(2):
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(rt.wait_pose(), 1.0)


def queue_for_speed(queue_size: int, speed: float) -> int:
    """The processing queue (scans) of a demo ``speed`` times faster than real time: as long in time as
    ``queue_size`` scans at real time (never shorter)."""
    return max(queue_size, math.ceil(queue_size * speed))


async def run_demo(opts: DemoOptions) -> DemoResult:
    """Start the emulated devices (a separate process), run the runtime against them, score the map.
    Never moves anything real: the devices are on a pseudo-terminal and on 127.0.0.1."""
    from glassmap.sim.robot import RobotParams
    from glassmap.sim.world import load_world
    from runtime.devices import DeviceProcess

    if opts.speed <= 0:
        raise ValueError(f"speed must be > 0, got {opts.speed}")
    world = load_world(opts.world)
    waypoints = world.route(opts.route)
    params = RobotParams()
    out = Path(opts.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = opts.config or RuntimeConfig()
    seen_path, truth_path = out / "seen_cells.npy", out / "true_poses.npy"
    devices = await DeviceProcess.start(opts.world, opts.speed, opts.seed, seen_path=str(seen_path),
                                        truth_path=str(truth_path))
    estimates: list[tuple[float, float, float, float]] = []  # per processed scan: stamp (ms, 24-bit), x, y, yaw
    truth_keys: dict[float, float] = {}  # scan stamp (host s) -> that stamp key, for the pose graph's key scans

    def on_result(r) -> None:
        if r.estimate is not None and r.scan.sensor_stamp is not None:
            key = float(round(r.scan.sensor_stamp * 1000) % (1 << 24))
            estimates.append((key, r.estimate.x, r.estimate.y, r.estimate.yaw))
            truth_keys[r.scan.stamp] = key

    report: dict = {}
    try:
        cfg.laser_url, cfg.base_url = devices.laser_url, devices.base_url
        cfg.base.enable_motors = True
        cfg.base.max_v, cfg.base.max_omega = opts.max_v, opts.max_omega
        m = cfg.mapping
        m.initial_x, m.initial_y, m.initial_yaw = (float(v) for v in world.start_pose)
        m.laser_x, m.laser_y, m.laser_yaw = (float(v) for v in params.laser_offset)
        m.deskew = False  # the emulated laser takes all beams of a scan from one pose (no sweep motion)
        m.registration = opts.registration or m.registration
        m.window = opts.window or m.window
        cfg.pipeline.queue_size = queue_for_speed(cfg.pipeline.queue_size, opts.speed)
        cfg.output.out_dir = str(out)
        cfg.output.record = str(out / "demo.mcap") if opts.record else ""

        bar = None
        if opts.progress:
            from tqdm import tqdm

            total = float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())
            bar = tqdm(total=round(total, 1), unit="m", desc=f"demo {world.name} x{opts.speed:g}",
                       bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} m [{elapsed}<{remaining}] {postfix}")

        last = [0.0]

        def progress(done: float, total: float) -> None:
            if bar is not None and time.monotonic() - last[0] > 0.5:
                last[0] = time.monotonic()
                bar.n = round(done, 1)
                st = rt.stage.stats if rt.stage else None
                if st is not None:
                    bar.set_postfix_str(f"scans {st.scans_processed}/{st.scans_received} "
                                        f"dropped {st.dropped_overflow + st.dropped_stale}", refresh=False)
                bar.refresh()

        driver = route_driver(waypoints, opts.speed, opts.max_v, opts.max_omega, progress)
        rt = Runtime(cfg, pioneer_options={"time_scale": opts.speed}, driver=driver, export_stem="glass_map",
                     on_result=on_result)
        cable_pull = None
        if opts.laser_link_loss_at is not None:
            async def pull_laser_cable() -> None:  # counted from the first processed scan, not from start-up
                while rt.latest is None:
                    await asyncio.sleep(0.02)
                await asyncio.sleep(opts.laser_link_loss_at / opts.speed)
                await devices.command("laser-disconnect")

            cable_pull = asyncio.create_task(pull_laser_cable())
        wall_limit = opts.duration / opts.speed if opts.duration is not None else None
        try:
            label = f"{opts.duration:g} s (emulated)" if opts.duration is not None else None
            summary = await rt.run(duration=wall_limit, duration_label=label)
        finally:
            if cable_pull is not None:
                cable_pull.cancel()
            if bar is not None:
                bar.close()
    finally:
        report = await devices.stop()
    evaluation = corrected_evaluation = None
    graph = getattr(rt.processor, "graph", None)
    try:
        seen = np.load(seen_path) if seen_path.exists() else None
        evaluation = evaluate_map(rt.processor.mapper, world, seen=seen)
        final_maps = graph.snapshot().glass if graph is not None else None
        if final_maps is not None:
            corrected_evaluation = evaluate_map(final_maps, world, seen=seen)
    except Exception as exc:  # the map is still written; say why there is no score
        log.error("evaluation against the blueprint failed: %s", exc)
    est = rt.pose.pose if rt.pose is not None else None
    est_cov = rt.pose.covariance if rt.pose is not None else None
    corrected = rt.latest.corrected_pose if rt.latest is not None else None
    trajectory = graph_eval = None
    true_final = np.full(3, np.nan)
    if truth_path.exists() and estimates:
        truth = np.load(truth_path)
        trajectory = evaluate_trajectory(np.asarray(estimates), truth)
        at = truth[truth[:, 0] == estimates[-1][0]]
        if len(at):
            true_final = at[-1, 1:].copy()
        if graph is not None:
            snap = graph.snapshot()
            keys = np.array([truth_keys.get(float(t), np.nan) for t in snap.stamps])
            graph_eval = evaluate_graph(keys, snap.poses, snap.accepted, truth, snap.stamps)
            if graph_eval is not None:
                graph_eval.write_csv(out / CLOSURES_FILE)
    return DemoResult(summary=summary, evaluation=evaluation, png=summary.exports.get("png", ""),
                      recording=cfg.output.record, true_final_pose=true_final, estimated_final_pose=est,
                      estimated_final_cov=est_cov, corrected_final=corrected,
                      closures=graph.closures if graph is not None else 0, graph=graph_eval,
                      corrected_evaluation=corrected_evaluation,
                      graph_lag=getattr(rt.processor, "graph_lag", 0),
                      true_pose_at_stop=np.asarray(report.get("true_pose", [np.nan] * 3)), trajectory=trajectory,
                      route_done=driver.follower.done,  # type: ignore[attr-defined]
                      latency=list(rt.latency.latency), stages=dict(rt.latency.stages),
                      device_report=report)


def final_error(res: DemoResult, corrected: bool = False) -> tuple[float, float] | None:
    """(m, sigma): the final position error, and the same in units of the reported covariance,
    sqrt(e^T P_xy^-1 e), of the front end's estimate or (``corrected``) of the pose graph's corrected one (None
    without that estimate or with a non-finite true pose)."""
    if corrected:
        c = res.corrected_final
        pose, cov = (None, None) if c is None else (c.pose, c.covariance)
    else:
        pose, cov = res.estimated_final_pose, res.estimated_final_cov
    if pose is None or cov is None:
        return None
    e = np.asarray(pose[:2]) - np.asarray(res.true_final_pose[:2])
    if not np.all(np.isfinite(e)):
        return None
    return float(np.hypot(*e)), float(np.sqrt(e @ np.linalg.solve(np.asarray(cov)[:2, :2], e)))


def format_result(res: DemoResult) -> str:
    s = res.summary
    lines = [f"stopped: {s.stop_reason} after {s.duration:.1f} s (wall clock)",
             f"{s.stages.summary()}; laser reconnects: {s.laser_reconnects}"]
    if res.trajectory is not None:
        lines.append(res.trajectory.describe())
    else:
        lines.append("pose error: not available (no true pose matched a processed scan)")
    fe = final_error(res)
    if fe is not None:
        k = fe[1]
        held = f" (held at rest {s.lost_held_s:.1f} s before recovering)" if s.lost_holds else ""
        lines.append(f"final pose error in the reported covariance: {k:.1f} sigma (xy Mahalanobis; "
                     f"{'inside' if k <= 3 else 'OUTSIDE'} 3 sigma); pose track {s.pose_status or '?'}, "
                     f"{s.pose_gated} scan matches rejected, lost {s.pose_lost} times{held}, ambiguous "
                     f"{s.pose_ambiguous} times")
    ce = final_error(res, corrected=True)
    if ce is not None:
        e, k = 100 * ce[0], ce[1]
        lines.append(f"corrected by the pose graph ({res.closures} loop closures, {res.graph_lag} key scans not yet "
                     f"in the graph): final error {e:.1f} cm, {k:.1f} sigma ({'inside' if k <= 3 else 'OUTSIDE'} 3 sigma)")
    if res.graph is not None:
        lines.append(res.graph.describe())
    if res.latency:
        lat = np.asarray(res.latency) * 1e3
        lines.append(f"latency scan bytes in -> maps updated: p50 {np.percentile(lat, 50):.1f} ms, "
                     f"p99 {np.percentile(lat, 99):.1f} ms")
    for k, v in s.exports.items():
        lines.append(f"map {k}: {v}")
    if res.recording:
        from runtime.output_args import describe_files

        stopped = "; stopped early, see the error above" if s.recording_error else ""
        lines.append(f"recording: {describe_files(s.recording_files) or res.recording} ({s.recorded_messages} "
                     f"messages, {s.recorder_dropped} dropped{stopped})")
    if s.live:
        lines.append(f"live view: {s.live} ({s.live_sent} messages sent, {s.live_dropped} dropped)")
    if res.evaluation is not None:
        lines.append(res.evaluation.describe())
    else:
        lines.append("classification error: not available (see the log)")
    if res.corrected_evaluation is not None:
        lines.append("corrected maps (key scans at the final pose graph's poses): "
                     + res.corrected_evaluation.describe())
    return "\n".join(lines)
