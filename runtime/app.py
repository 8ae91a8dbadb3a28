"""The on-robot application: one asyncio task per device, the processing stage, the recorder, map export.

    laser task  --Scan-->  ProcessingStage (bounded queue, processing thread)  --ScanResult-->  recorder, pose
    base task   --Odometry-->        |                                                       (for a driver)
    export task: maps to out_dir every export_period s, /map and /glass/map every map_publish_period s,
                 both made from a copy of the maps by the map worker process (runtime.map_worker)
    driver task (optional): route following (demo) or keyboard teleoperation; nothing else moves the robot

Shutdown (Ctrl-C, SIGTERM, ``duration`` reached, or any task failing, e.g. a crash in processing): the
robot is stopped and disabled first, then the laser stream stopped, the queued scans processed, the maps
exported, the recording finished. :meth:`Runtime.run` then re-raises the failure, if any.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import sys
import time
from collections.abc import Awaitable, Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

from glassmap.types import Odometry, PoseEstimate
from runtime.config import RuntimeConfig
from runtime.live import Fanout, LiveView, start_live_view
from runtime.map_worker import MapWorker, map_messages
from runtime.messages import TimeBase, as_recorded_odometry, as_recorded_scan, warm_up_serializers
from runtime.pipeline import ProcessingStage, ScanResult, StageStats
from runtime.processor import MappingProcessor
from runtime.recorder import McapRecorder, RecorderError
from runtime.shutdown import StopRequest, handle_signals
from runtime.sink import RecordingSink, RosoutHandler, recording_metadata
from runtime.tuning import freeze_startup, release_heap_reserve, reserve_heap, thaw

log = logging.getLogger(__name__)

Driver = Callable[["Runtime"], Awaitable[None]]


class RuntimeFailure(RuntimeError):
    """The runtime stopped because a device or the processing failed (the message says which)."""


@dataclass
class LatencyLog:
    """Per-scan figures: bytes-in -> maps-updated latency (s) and per-stage times (s)."""

    latency: list[float] = field(default_factory=list)
    stages: dict[str, list[float]] = field(default_factory=dict)

    def add(self, r: ScanResult) -> None:
        if r.bytes_in_time is not None:
            self.latency.append(r.done_time - r.bytes_in_time)
        for k, v in r.timings.items():
            self.stages.setdefault(k, []).append(v)


@dataclass
class RunSummary:
    """What a run did (counters, files written)."""

    stages: StageStats = field(default_factory=StageStats)
    laser_reconnects: int = 0
    base_reconnects: int = 0
    recording: str = ""
    recorded_messages: int = 0
    recorder_dropped: int = 0
    recording_files: list[str] = field(default_factory=list)  # one unless the recording was split
    recording_error: str = ""  # why the recording stopped early (disk full, ...), "" if it did not
    live: str = ""  # the live view's WebSocket URL
    live_sent: int = 0
    live_dropped: int = 0
    exports: dict[str, str] = field(default_factory=dict)
    stop_reason: str = ""
    duration: float = 0.0
    pose_status: str = ""  # the pose estimator's track status at the end ("ok", "degraded", "lost")
    pose_gated: int = 0  # scan matches rejected by the estimator's gate (neither fused nor mapped)
    pose_lost: int = 0  # times the track was lost
    pose_ambiguous: int = 0  # streaks of rejected matches judged aliases (followed odometry)
    lost_holds: int = 0  # times a driven robot was held at rest on a lost track (base.lost_hold)
    lost_held_s: float = 0.0  # time (s, the robot's) it was held before the track recovered

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class Runtime:
    """One run of the robot program. Build it, then ``await runtime.run()``.

    hokuyo_options / pioneer_options: fields of ``HokuyoSettings`` / ``PioneerSettings`` that replace the
    ones made from the config (e.g. ``{"time_scale": 4.0}`` for emulators running 4x faster).
    """

    def __init__(self, config: RuntimeConfig, *, processor: MappingProcessor | None = None,
                 hokuyo_options: dict | None = None, pioneer_options: dict | None = None,
                 driver: Driver | None = None, stop: StopRequest | None = None,
                 on_result: Callable[[ScanResult], None] | None = None, export_stem: str = "glass_map") -> None:
        config.validate()
        self.config = config
        self.processor = processor or MappingProcessor(config.mapping)
        self._graph_version = 0  # the last pose-graph snapshot recorded
        self.hokuyo_options = dict(hokuyo_options or {})
        self.pioneer_options = dict(pioneer_options or {})
        self.driver = driver
        self.stop = stop
        self.on_result_cb = on_result
        self.export_stem = export_stem
        self.time_base = TimeBase.now()
        self.latest: ScanResult | None = None
        self.latest_odom: Odometry | None = None
        self.laser = None
        self.base = None
        self.latency = LatencyLog()
        self.summary = RunSummary()
        self.stage: ProcessingStage | None = None
        self.recorder: McapRecorder | None = None
        self.sink: RecordingSink | None = None
        self.live: LiveView | None = None
        self._rx_time: dict[str, float] = {}
        self.map_worker = MapWorker()
        self._pose_event = asyncio.Event()
        self._lost_since: float | None = None  # scan stamp (s) at which the robot was held on a lost track
        self._hold_task: asyncio.Task | None = None

    # -- helpers for drivers (route following, teleop) ---------------------------------------------------
    @property
    def pose(self) -> PoseEstimate | None:
        """The latest pose estimate of the base (map frame), or None before the first processed scan."""
        return self.latest.estimate if self.latest is not None else None

    async def wait_pose(self) -> PoseEstimate:
        """Wait for the next processed scan's pose."""
        self._pose_event.clear()
        await self._pose_event.wait()
        return self.pose

    async def command_velocity(self, v: float, omega: float) -> None:
        """Send a velocity command (m/s, rad/s) to the base and record it on /cmd_vel; zero while the robot is
        held on a lost pose track."""
        if self.base is None:
            raise RuntimeFailure("no base connected: cannot drive")
        if self._lost_since is not None:
            v, omega = 0.0, 0.0
        await self.base.set_velocity(v, omega)
        if self.sink is not None:
            self.sink.cmd_vel(time.monotonic(), v, omega)

    # -- the run ----------------------------------------------------------------------------------------
    async def run(self, duration: float | None = None, duration_label: str | None = None) -> RunSummary:
        """Run until ``duration`` seconds (wall clock) have passed, a stop is requested, or a task fails.
        ``duration_label`` names the limit in the stop reason (default "<duration> s")."""
        cfg = self.config
        stop = self.stop or StopRequest()
        self.stop = stop
        t_start = time.monotonic()
        rosout = None
        if cfg.output.record:
            meta = recording_metadata(self.time_base, laser_url=cfg.resolved_laser_url(),
                                      base_url=cfg.resolved_base_url(),
                                      base_time_scale=self.pioneer_options.get("time_scale", 1.0),
                                      base_model=self.pioneer_options.get("model") or "",
                                      mapping=json.dumps(dataclasses.asdict(cfg.mapping)))
            self.recorder = McapRecorder(cfg.output.record, chunk_size=cfg.output.chunk_size,
                                         chunk_interval=cfg.output.chunk_interval,
                                         compression=cfg.output.compression, metadata=meta,
                                         split_size=cfg.output.record_split_size,
                                         split_duration=cfg.output.record_split_duration)
            self.summary.recording = str(cfg.output.record)
        if cfg.output.live:
            try:
                self.live = start_live_view(cfg.output)
            except BaseException:
                if self.recorder is not None:
                    self.recorder.close()
                raise
            self.summary.live = self.live.url
            # the operator needs this address: on the console whatever the log level
            print(f"live view: {self.live.url} (Foxglove: Open connection -> Foxglove WebSocket URL)",
                  file=sys.stderr, flush=True)
        if self.recorder is not None or self.live is not None:
            out = Fanout(self.recorder, self.live)
            self.sink = RecordingSink(out, self.time_base, laser_frame=cfg.laser.laser_frame_id,
                                      base_frame=cfg.base.base_link_frame, odom_frame=cfg.base.odom_frame,
                                      map_frame=cfg.mapping.map_frame,
                                      record_raw=cfg.output.record_raw and self.recorder is not None)
            rosout = RosoutHandler(out, self.time_base)
            log_state = _record_info_logs(rosout)
        self.stage = ProcessingStage(self.processor, queue_size=cfg.pipeline.queue_size,
                                     max_scan_age=cfg.pipeline.max_scan_age, odom_buffer=cfg.pipeline.odom_buffer,
                                     on_result=self._on_result, nice=cfg.pipeline.nice)
        failure: BaseException | None = None
        reserved = False
        try:
            with handle_signals(stop):
                # before the devices connect, so that the first scans are not delayed by start-up work
                await self.stage.call(self.processor.warm_up)
                warm_up_serializers()  # the ROS type store and its CDR code, before the first messages need them
                await self.map_worker.start()
                freeze_startup()  # start-up objects out of the garbage collector's way (runtime.tuning)
                reserved = reserve_heap(cfg.pipeline.memory_reserve << 20)  # pages for the first grid growths
                await self._connect()
                tasks = [asyncio.create_task(self._laser_task(), name="laser"),
                         asyncio.create_task(self.stage.run(), name="processing"),
                         asyncio.create_task(self._export_task(), name="export")]
                if self.base is not None:
                    tasks.append(asyncio.create_task(self._base_task(), name="base"))
                if self.driver is not None:
                    tasks.append(asyncio.create_task(self._driver_task(), name="driver"))
                stopper = asyncio.create_task(stop.wait(), name="stop")
                waiters = [*tasks, stopper]
                try:
                    done, _ = await asyncio.wait(waiters, timeout=duration, return_when=asyncio.FIRST_COMPLETED)
                    if not done:
                        stop.set(f"duration {duration_label or f'{duration:g} s'} reached")
                    for t in done:
                        if t is stopper:
                            continue
                        if t.exception() is not None:
                            failure = t.exception()
                            stop.set(f"{t.get_name()} failed: {failure}")
                        elif t.get_name() == "driver":
                            stop.set("driver finished (route done or teleop quit)")
                        else:
                            stop.set(f"{t.get_name()} ended")
                finally:
                    await self._shutdown([t for t in tasks if t.get_name() != "processing"], stopper)
                    proc = next(t for t in tasks if t.get_name() == "processing")
                    await self._finish_processing(proc)
        finally:
            thaw()
            if reserved:
                release_heap_reserve()
            await self._close_devices()
            if self.stage is not None:
                self.stage.shutdown()
            self.map_worker.shutdown()
            self.summary.stop_reason = stop.reason
            self.summary.duration = time.monotonic() - t_start
            self._fill_summary()
            if self.sink is not None:
                self.sink.summary(time.monotonic(), self.summary.as_dict())
            if rosout is not None:
                _restore_logs(rosout, log_state)
            if self.live is not None:
                self.live.close()
                self.summary.live_sent = self.live.stats.total_sent
                self.summary.live_dropped = self.live.stats.total_dropped
            if self.recorder is not None:
                try:
                    self.recorder.close()
                except RecorderError as exc:  # logged once when it happened; the run itself went on
                    self.summary.recording_error = str(exc)
                self.summary.recorded_messages = self.recorder.stats.total_written
                self.summary.recorder_dropped = self.recorder.stats.total_dropped
                self.summary.recording_files = list(self.recorder.stats.files)
        if failure is not None:
            raise RuntimeFailure(f"run stopped: {stop.reason}") from failure
        return self.summary

    async def _connect(self) -> None:
        """Connect the base, then the laser. The laser streams from its connect on and its scans wait until
        the laser task starts; connected first, the scans of the base's handshake would reach the processing
        queue at once. If either fails, run()'s clean-up closes what did connect (the base stopped)."""
        from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
        from drivers.pioneer.client import PioneerClient, PioneerSettings

        cfg = self.config
        base_url = cfg.resolved_base_url()
        if base_url.lower() not in ("", "none"):
            btaps = [self.sink.tap("base", base_url)] if self.sink is not None else []
            popts = {"max_v": cfg.base.max_v, "max_omega": cfg.base.max_omega, **self.pioneer_options}
            self.base = await PioneerClient.connect(base_url, PioneerSettings(**popts), taps=btaps,
                                                    enable_motors=cfg.base.enable_motors)
            log.info("base connected: %s (motors %s)", base_url, "enabled" if cfg.base.enable_motors else "disabled")
        laser_url = cfg.resolved_laser_url()
        taps = [self._rx_tap("laser")]
        if self.sink is not None:
            taps.append(self.sink.tap("laser", laser_url))
        multi = {"on": True, "off": False}.get(cfg.laser.multi_echo, self.processor.wants_echoes)
        opts = {"cluster": cfg.laser.cluster, "skip": cfg.laser.skip, "multi_echo": multi, **self.hokuyo_options}
        self.laser = await HokuyoClient.connect(laser_url, HokuyoSettings(**opts), taps=taps)
        log.info("laser connected: %s", laser_url)

    def _rx_tap(self, device: str):
        def tap(direction: str, host_time: float, data: bytes) -> None:
            if direction == "rx":
                self._rx_time[device] = host_time
        return tap

    async def _laser_task(self) -> None:
        async for scan in self.laser.scans():
            scan = as_recorded_scan(scan, self.time_base)
            if self.sink is not None:
                self.sink.scan(scan)
            self.stage.submit_scan(scan, self._rx_time.get("laser"))

    async def _base_task(self) -> None:
        async for odom in self.base.odometry():
            odom, msg = as_recorded_odometry(odom, self.time_base, self.config.base.odom_frame,
                                             self.config.base.base_link_frame)
            self.latest_odom = odom
            if self.sink is not None:
                self.sink.odometry(odom, msg)
            self.stage.submit_odometry(odom)
        if not self.stop.is_set():
            raise RuntimeFailure("the base link closed")

    async def _driver_task(self) -> None:
        await self.driver(self)

    def _on_result(self, r: ScanResult) -> None:
        self.latest = r
        if self.driver is not None and self.stop is not None:
            self._hold_while_lost(r)
            self._stop_if_too_uncertain(r)
        self.latency.add(r)
        if self.sink is not None:
            self.sink.result(r)
        if self.on_result_cb is not None:
            self.on_result_cb(r)
        self._pose_event.set()

    def _hold_while_lost(self, r: ScanResult) -> None:
        """Never drive on an estimate that no longer agrees with the map: while the track is lost the robot is
        held at rest (every command becomes zero) for up to ``base.lost_hold`` s of the robot's time, for the
        estimator to relocalise against the map; then driving goes on, or, if it has not, the run stops and
        says why."""
        stamp, lost = float(r.scan.stamp), r.estimate.status == "lost"
        scale = self.pioneer_options.get("time_scale", 1.0)  # robot seconds per host second (stamps: host s)
        hold = self.config.base.lost_hold / scale
        if lost and self._lost_since is None:
            self._lost_since = stamp
            self.summary.lost_holds += 1
            if hold > 0:
                log.warning("pose track lost at t=%.1f s: holding the robot at rest for up to %g s while the "
                            "estimate relocalises against the map", stamp, self.config.base.lost_hold)
            if self.base is not None and (self._hold_task is None or self._hold_task.done()):
                self._hold_task = asyncio.get_running_loop().create_task(self._command_rest())
        elif not lost and self._lost_since is not None:
            held = (stamp - self._lost_since) * scale
            self.summary.lost_held_s += held
            log.warning("pose track recovered at t=%.1f s after %.2f s held at rest: driving on", stamp, held)
            self._lost_since = None
        if lost and stamp - self._lost_since >= hold:
            st = self.processor.estimator.stats
            waited = f"; not recovered within {self.config.base.lost_hold:g} s held at rest" if hold > 0 else ""
            self.stop.set(f"pose estimate lost at t={self._lost_since:.1f} s: {st.status_reason}{waited}")

    def _stop_if_too_uncertain(self, r: ScanResult) -> None:
        """Never drive on an estimate too uncertain to follow a route: once the reported position standard
        deviation (widest direction; the corrected estimate's with loop closure) exceeds ``base.max_sigma``, the
        run stops and says why (relocalisations add their jumps to it, docs/pose.md)."""
        limit = self.config.base.max_sigma
        est = r.corrected_pose if r.corrected_pose is not None else r.estimate
        if limit <= 0 or est is None or self.stop.is_set():
            return
        sigma = est.sigma_xy
        if sigma > limit:
            st = self.processor.estimator.stats
            self.stop.set(f"pose estimate too uncertain at t={float(r.scan.stamp):.1f} s: position standard deviation "
                          f"{sigma:.2f} m > base.max_sigma {limit:g} m (track {st.status}, lost {st.lost_events} "
                          f"times); the robot is stopped")
            if self.base is not None and (self._hold_task is None or self._hold_task.done()):
                self._hold_task = asyncio.get_running_loop().create_task(self._command_rest())

    async def _command_rest(self) -> None:
        """Zero velocity now (the driver's next command would come up to one period later)."""
        from drivers.errors import DriverError

        with contextlib.suppress(DriverError):
            await self.command_velocity(0.0, 0.0)

    async def _export_task(self) -> None:
        out = self.config.output
        next_export = time.monotonic() + out.export_period if out.export_period > 0 else math.inf
        next_pub = time.monotonic() + out.map_publish_period if out.map_publish_period > 0 else math.inf
        while True:
            await asyncio.sleep(max(0.05, min(next_export, next_pub) - time.monotonic()))
            now = time.monotonic()
            publish, export = now >= next_pub, now >= next_export
            if publish:
                next_pub = now + out.map_publish_period
            if export:
                next_export = now + out.export_period
            if self.latest is None or not ((publish and self.sink is not None) or export):
                continue
            # copy the maps in the processing thread (between two scans), convert and write them elsewhere
            maps = await self.stage.call(self.processor.copy_maps)
            if publish and self.sink is not None:
                await self._publish_maps(maps)
                await self._publish_graph()
            if export:
                await self._export_maps(maps)

    async def _export_maps(self, maps) -> None:
        out = self.config.output
        try:
            self.summary.exports = await self.map_worker.export(maps, out.out_dir, self.export_stem)
            log.info("maps exported to %s", out.out_dir)
        except (OSError, BrokenProcessPool) as exc:  # keep mapping (and the robot safe); say why
            log.error("map export to %s failed: %s", out.out_dir, exc)

    async def _publish_maps(self, maps) -> None:
        """/map and /glass/map from a copy of the maps (built and serialised by the map worker)."""
        ns = self.time_base.ns(time.monotonic())
        try:
            occ, glass = await self.map_worker.map_messages(maps, ns, self.config.mapping.map_frame)
        except BrokenProcessPool as exc:
            log.error("map messages not recorded: %s", exc)
            return
        self.sink.maps(ns, occ, glass)

    async def _publish_graph(self) -> None:
        """The pose graph's trajectory and corrected maps, when a loop closure has produced new ones (built
        and serialised by the map worker)."""
        graph = getattr(self.processor, "graph", None)
        if graph is None:
            return
        snap = graph.snapshot()
        if snap.version > self._graph_version:
            self._graph_version = snap.version
            ns = self.time_base.ns(time.monotonic())
            try:
                msgs = await self.map_worker.graph_messages(snap, ns, self.config.mapping.map_frame, self.time_base)
            except BrokenProcessPool as exc:
                log.error("pose graph messages not recorded: %s", exc)
                return
            self.sink.cdr(ns, msgs)

    async def _shutdown(self, tasks: list[asyncio.Task], stopper: asyncio.Task) -> None:
        """Cancel the driver (no further commands), stop the robot, then cancel the device and export tasks."""
        for t in tasks:
            if t.get_name() == "driver":
                t.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await t
        if self.base is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.base.stop(), 1.0)
        for t in [*tasks, stopper]:
            t.cancel()
        for t in [*tasks, stopper]:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t

    async def _finish_processing(self, proc: asyncio.Task) -> None:
        """Process what is queued (bounded wait), then export the maps one last time."""
        self.stage.close()
        try:
            await asyncio.wait_for(asyncio.shield(proc), 5.0)
        except asyncio.TimeoutError:
            proc.cancel()
        except Exception:
            pass  # reported by run() already if it was the failure
        if not proc.done():
            proc.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await proc
        if self.latest is not None:
            try:
                out = self.config.output
                maps = await self.stage.call(self.processor.copy_maps)
                if self.sink is not None:
                    ns = self.time_base.ns(time.monotonic())
                    self.sink.maps(ns, *await self._final(map_messages, maps, ns, self.config.mapping.map_frame))
                self.summary.exports = await self._final(maps.export, out.out_dir, self.export_stem)
            except Exception as exc:
                log.error("final map export failed: %s", exc)
            await self._finish_graph()

    async def _final(self, fn, *args):
        """``fn(*args)`` in the map worker (the runtime never imports matplotlib: +29 MiB), or in a thread of
        this process if the worker is gone: the last maps never depend on the map worker."""
        try:
            return await self.map_worker.run(fn, *args)
        except BrokenProcessPool as exc:
            log.warning("map worker gone (%s): the final maps are made in this process", exc)
            return await asyncio.to_thread(fn, *args)

    async def _finish_graph(self) -> None:
        """With loop closure: wait for the pose graph, record its optimised trajectory and corrected map."""
        if getattr(self.processor, "graph", None) is None:
            return
        try:
            snap = await asyncio.to_thread(self.processor.finish_graph)
            if self.sink is not None:
                self.sink.pose_graph(self.time_base.ns(time.monotonic()), snap)
            log.info("pose graph: %d key scans, %d loop closures", len(snap.stamps), snap.closures)
        except Exception as exc:
            log.error("pose graph not recorded: %s", exc)

    async def _close_devices(self) -> None:
        """Robot stopped, motors disabled, CLOSE (PioneerClient.close); laser QT (HokuyoClient.close)."""
        if self.base is not None:
            self.summary.base_reconnects = getattr(self.base.stats, "reconnects", 0)
            try:
                await asyncio.wait_for(self.base.close(), 3.0)
            except Exception as exc:
                log.error("closing the base failed: %s", exc)
        if self.laser is not None:
            self.summary.laser_reconnects = getattr(self.laser.stats, "reconnects", 0)
            try:
                await asyncio.wait_for(self.laser.close(), 3.0)
            except Exception as exc:
                log.error("closing the laser failed: %s", exc)

    def _fill_summary(self) -> None:
        if self.stage is not None:
            self.summary.stages = self.stage.stats
        est = getattr(self.processor, "estimator", None)
        if est is not None:
            s = self.summary
            s.pose_status, s.pose_gated, s.pose_lost = est.stats.status, est.stats.gated, est.stats.lost_events
            s.pose_ambiguous = est.stats.ambiguous_events


def _record_info_logs(handler: logging.Handler):
    """Attach ``handler`` (/rosout) to the root logger and let INFO records reach it, without making the
    console more verbose (console handlers keep the level the root logger had)."""
    root = logging.getLogger()
    state = (root.level, [(h, h.level) for h in root.handlers])
    console_level = root.level or logging.WARNING
    for h in root.handlers:
        if h.level == logging.NOTSET:
            h.setLevel(console_level)
    root.addHandler(handler)
    root.setLevel(min(console_level, logging.INFO))
    return state


def _restore_logs(handler: logging.Handler, state) -> None:
    root = logging.getLogger()
    root.removeHandler(handler)
    level, handlers = state
    root.setLevel(level)
    for h, lvl in handlers:
        h.setLevel(lvl)
