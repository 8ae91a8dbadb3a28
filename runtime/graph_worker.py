"""The pose-graph worker: runs the SLAM back end in a helper process, off the 40 Hz scan path.

iSAM2 updates, loop-closure checks (a submap field and a correlative match) and corrected-map rebuilds hold
the GIL for up to ~1 s; in a thread of the runtime's process that time would be taken from the scans. The
back end therefore runs in its own process (spawned, not forked: the runtime has threads; niced, so that
on a busy machine the scans come first). The processing thread hands over each key scan
(:meth:`GraphWorker.submit`, never blocks: a queue's feeder thread pickles it; the estimator's
``last_key_scan`` with the raw scan and its p(glass)); the worker process adds it to the
:class:`~glassmap.pose.backend.GraphBackEnd` (iSAM2, submaps, loop-closure checks) and sends back the
correction after each key scan. After accepted loop closures (once it has caught up with its queue, at most
every ``rebuild_period`` s) and when asked at the end of a run (:meth:`GraphWorker.finish`), it
re-integrates the key scans at the optimised poses into a corrected occupancy grid and, when the key scans
carry p(glass), a corrected glass map (:class:`glassmap.pose.corrected.MapRebuild`), and sends them back.
The periodic rebuild goes on ``REBUILD_STEP`` key scans at a time while no key scan is waiting: a whole one
takes seconds on a long loop, and the corrections (which the runtime applies to every scan) must not wait
for it.
A reader thread in the runtime's process takes in what comes back; readers take snapshots under a lock.

Every key scan is processed in order and intermediate maps are read without touching the graph
(``GraphBackEnd.poses(refresh=False)``), so a replay of a recording reproduces the final graph exactly.
A worker that raises, or whose process dies, is reported (:class:`GraphWorkerError` from :meth:`finish`,
``error``) instead of being waited for; the scans go on without the back end. If the process cannot start
(spawning must import the main module, impossible for some embedded interpreters), the back end runs in a
thread of this process instead, with a warning.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import threading
import time
import traceback
from dataclasses import dataclass, replace

import numpy as np

from glassmap.grid import OccupancyGrid, OccupancyParams
from glassmap.mapping import MapCopy, MapperConfig
from glassmap.pose.backend import BackEndConfig, GraphCorrection
from glassmap.pose.keyscan import KeyScan

log = logging.getLogger(__name__)

START_TIMEOUT = 60.0  # s for the process to import what it needs and say it is ready


class GraphWorkerError(RuntimeError):
    """The pose-graph worker failed (an exception in the back end, or its process died)."""


@dataclass
class GraphSnapshot:
    """What the worker has published: stamps (N,) s and poses (N, 3) of the optimised key scans (map
    frame), the number of accepted loop closures, the corrected occupancy grid and glass map (a
    :class:`~glassmap.mapping.MapCopy` on the same grid; None before the first closure or
    :meth:`GraphWorker.finish`; the glass map also without a mapper config), ``version`` (incremented
    on every new corrected map) and the accepted closures themselves (:class:`~glassmap.pose.backend.Closure`,
    nodes indexing ``stamps``)."""

    stamps: np.ndarray
    poses: np.ndarray
    closures: int
    grid: OccupancyGrid | None
    version: int
    glass: MapCopy | None = None
    accepted: tuple = ()


@dataclass(frozen=True)
class _Settings:
    """What the worker process needs to build the back end (picklable)."""

    config: BackEndConfig
    sigma_hit: float
    occupancy: OccupancyParams
    resolution: float
    mapper: MapperConfig | None
    rebuild_period: float


class GraphWorker:
    """A :class:`~glassmap.pose.backend.GraphBackEnd` in a helper process (see the module docstring).

    in_process=True runs it in a thread of this process instead (tests, or where no process can start)."""

    def __init__(self, config: BackEndConfig = BackEndConfig(), sigma_hit: float = 0.03,
                 occupancy: OccupancyParams = OccupancyParams(), resolution: float = 0.05,
                 mapper: MapperConfig | None = None, rebuild_period: float = 5.0, in_process: bool = False) -> None:
        self._settings = _Settings(config, sigma_hit, occupancy, resolution, mapper, rebuild_period)
        self._lock = threading.Condition()
        self._correction = None  # the back end's latest GraphCorrection (None before its first key scan)
        self._snapshot = GraphSnapshot(np.zeros(0), np.zeros((0, 3)), 0, None, 0)
        self._submitted = 0
        self._done = 0  # key scans the back end has taken in
        self._final: GraphSnapshot | None = None
        self._finish_token = 0
        self._closing = False
        self.busy_time = 0.0  # s (wall clock of the worker) spent in the back end and building corrected maps
        self.closures = 0
        self.map_seconds = 0.0  # s the worker took to build the latest corrected maps
        self.error: GraphWorkerError | None = None
        self.in_process = in_process
        self._process = None
        if not in_process:
            try:
                self._start_process()
            except GraphWorkerError as exc:
                log.warning("%s; the pose graph runs in a thread of this process instead (scans are slower while "
                            "it optimises)", exc)
                self.in_process = True
        if self.in_process:
            self._inbox, self._outbox = queue.SimpleQueue(), queue.SimpleQueue()
            self._thread = threading.Thread(target=serve, args=(self._inbox, self._outbox, self._settings),
                                            name="pose-graph", daemon=True)
            self._thread.start()
        self._reader = threading.Thread(target=self._read, name="pose-graph-reader", daemon=True)
        self._reader.start()

    def _start_process(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._inbox, self._outbox = ctx.Queue(), ctx.Queue()
        self._inbox.cancel_join_thread()  # never wait at exit to hand a dead worker what it will not read
        self._process = ctx.Process(target=serve, args=(self._inbox, self._outbox, self._settings, os.getpid()),
                                    name="pose-graph", daemon=True)
        try:
            self._process.start()
        except (AssertionError, OSError) as exc:  # e.g. inside a daemonic process, which may have no children
            self._process = None
            raise GraphWorkerError(f"the pose-graph worker process could not start ({exc})") from exc
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            try:
                msg = self._outbox.get(timeout=0.2)
            except queue.Empty:
                msg = None
            if msg is not None and msg[0] == "ready":
                return
            if not self._process.is_alive() or time.monotonic() > deadline:
                code = self._process.exitcode
                self._process.kill()
                self._process.join(1.0)
                self._process = None
                raise GraphWorkerError(f"the pose-graph worker process did not start (exit code {code})")

    # -- the processing thread's side ------------------------------------------------------------------
    def submit(self, key: KeyScan) -> None:
        """Queue one key scan (from the processing thread; returns at once). Dropped once the worker failed."""
        if self.error is not None or self._closing:
            return
        with self._lock:
            self._submitted += 1
        self._inbox.put(("key", compact(key)))

    def latest_correction(self) -> tuple[GraphCorrection | None, int]:
        """The back end's latest :class:`~glassmap.pose.backend.GraphCorrection` (None before it has taken in a
        key scan) and the key scans submitted since that are not yet in the graph."""
        with self._lock:
            return self._correction, self._submitted - self._done

    def snapshot(self) -> GraphSnapshot:
        with self._lock:
            return self._snapshot

    @property
    def pending(self) -> int:
        """Key scans submitted and not yet in the graph."""
        with self._lock:
            return self._submitted - self._done

    def finish(self, timeout: float = 60.0) -> GraphSnapshot:
        """Wait until every submitted key scan is in the graph, build the corrected maps at the final
        solution, and return the snapshot. Raises GraphWorkerError if the worker failed or died, TimeoutError
        if it does not catch up in time."""
        with self._lock:
            self._finish_token += 1
            token = self._finish_token
            self._final = None
        self._inbox.put(("finish", token))
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._final is None and self.error is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"the pose-graph worker still has {self._submitted - self._done} key scans "
                                       f"after {timeout} s")
                self._lock.wait(min(left, 0.5))
            if self.error is not None:
                raise self.error
            return self._final

    def close(self, timeout: float = 5.0) -> None:
        """Stop the worker once it has taken in what is queued, waiting up to ``timeout`` s; a process that
        takes longer is killed (a thread is left to end on its own: it is a daemon)."""
        if self._closing:
            return
        self._closing = True
        self._inbox.put(None)
        if self._process is not None:
            self._process.join(timeout)
            if self._process.is_alive():
                log.warning("the pose-graph worker did not stop within %.0f s; killed", timeout)
                self._process.kill()
                self._process.join(1.0)
        else:
            self._thread.join(timeout)
        self._reader.join(timeout)

    # -- the reader thread -------------------------------------------------------------------------------
    def _alive(self) -> bool:
        return self._process.is_alive() if self._process is not None else self._thread.is_alive()

    def _read(self) -> None:
        while True:
            try:
                msg = self._outbox.get(timeout=0.5)
            except queue.Empty:
                if self._alive():
                    continue
                if not self._closing:
                    code = self._process.exitcode if self._process is not None else None
                    self._fail(GraphWorkerError(f"the pose-graph worker process ended unexpectedly (exit code "
                                                f"{code}); the scans go on without loop closure"))
                return
            except (EOFError, OSError) as exc:  # the pipe broke: the process is gone
                if not self._closing:
                    self._fail(GraphWorkerError(f"lost the pose-graph worker ({type(exc).__name__}: {exc})"))
                return
            kind = msg[0]
            if kind == "done":
                _, done, corr, busy = msg
                closures = corr.closures
                with self._lock:
                    self._done, self._correction, self.busy_time = done, corr, busy
                    if closures > self.closures:
                        log.info("loop closure: %d accepted in all (%d key scans)", closures, done)
                    self.closures = closures
            elif kind == "maps":
                _, token, stamps, poses, accepted, occ, glass, seconds = msg
                with self._lock:
                    self.map_seconds = seconds
                    old = self._snapshot
                    self._snapshot = GraphSnapshot(stamps, poses, len(accepted), occ, old.version + 1, glass, accepted)
                    if token is not None and token == self._finish_token:
                        self._final = self._snapshot
                    self._lock.notify_all()
            elif kind == "error":
                self._fail(GraphWorkerError(f"the pose-graph worker failed: {msg[1]}"))
            elif kind == "stopped":
                return

    def _fail(self, err: GraphWorkerError) -> None:
        log.error("%s", err)
        with self._lock:
            self.error = err
            self._lock.notify_all()


def graph_messages(snapshot: GraphSnapshot, stamp_ns: int, frame_id: str, time_base) -> list[tuple[str, bytes]]:
    """CDR of ``/pose_graph/path`` (the optimised key scans, stamped through ``time_base``, a
    :class:`runtime.messages.TimeBase`) and, with the corrected maps, ``/map/corrected`` and
    ``/glass/map/corrected``, as (topic, bytes), in whatever process calls it: building them holds the GIL
    for ~0.1 s on a 50 x 40 m grid, so the runtime has its map worker do it."""
    from runtime import messages as M

    msgs = [("/pose_graph/path", M.path_msg([time_base.ns(t) for t in snapshot.stamps], snapshot.poses, stamp_ns,
                                            frame_id))]
    if snapshot.grid is not None:
        g = snapshot.grid.grid
        msgs.append(("/map/corrected", M.occupancy_grid_msg(snapshot.grid.probability(), tuple(g.origin),
                                                            g.resolution, stamp_ns, frame_id)))
    if snapshot.glass is not None:
        g = snapshot.glass.grid
        msgs.append(("/glass/map/corrected", M.glass_grid_msg(snapshot.glass.confidence_map(), tuple(g.origin),
                                                              g.resolution, stamp_ns, frame_id)))
    ts = M.typestore()
    return [(topic, bytes(ts.serialize_cdr(m, M.TOPICS[topic]))) for topic, m in msgs]


def compact(key: KeyScan) -> KeyScan:
    """The key scan without what the back end never reads: the raw scan keeps its ranges, geometry and
    stamps (the corrected glass map's steps read only those), not its intensities and extra echoes."""
    if key.scan is None:
        return key
    return replace(key, scan=replace(key.scan, intensities=None, echoes=None, echo_intensities=None))


# -- run in the worker process (or thread) ----------------------------------------------------------------
REBUILD_STEP = 20  # key scans a periodic map rebuild integrates between looks at the inbox (~1-2 ms each)


def serve(inbox, outbox, settings: _Settings, parent_pid: int | None = None) -> None:
    """The worker's loop: messages ("key", KeyScan), ("finish", token) or None (stop) from ``inbox``;
    ("done", n, GraphCorrection, busy s), ("maps", token, stamps, poses, accepted closures, grid, glass, s to build them),
    ("error", text), ("stopped",) to ``outbox``. ``parent_pid``: in a process, end when that process is gone."""
    if parent_pid is not None:
        _process_setup(parent_pid)
    from glassmap.pose.backend import GraphBackEnd
    from runtime.tuning import release_compiler_pages

    be = GraphBackEnd(settings.config, settings.sigma_hit)
    outbox.put(("ready",))
    busy, dirty, last_rebuild, failed = 0.0, False, -float("inf"), False
    rebuild = None  # the periodic map rebuild in progress: (MapRebuild, stamps, poses, closures, CPU s so far)
    # the kernels load at the first closure check and the first map rebuild: after each, LLVM's pages go
    # (runtime.tuning)
    loaded: set[str] = set()

    def report(exc: Exception) -> None:  # to the runtime; the scans go on without the back end
        outbox.put(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))

    def loaded_now(what: str) -> None:
        if what not in loaded:
            loaded.add(what)
            release_compiler_pages()

    def start_rebuild(refresh: bool):
        nonlocal dirty, last_rebuild
        dirty, last_rebuild = False, time.monotonic()
        poses = be.poses(refresh=refresh)
        job = be.map_rebuild(settings.occupancy, settings.resolution, poses, settings.mapper)
        return job, be.stamps(), poses, tuple(be.closures), 0.0

    def send_maps(token, job, stamps, poses, closures, seconds: float) -> None:
        occ = glass = None
        if len(stamps):
            occ = job.occ
            if job.glass is not None:
                glass = job.glass.copy_maps()
                occ = glass.occupancy
        outbox.put(("maps", token, stamps, poses, closures, occ, glass, seconds))
        loaded_now("maps")

    while True:
        if rebuild is not None and _empty(inbox):
            # the periodic rebuild goes on a few key scans at a time, so that new key scans (and the
            # corrections the runtime reports with them) never wait for a whole rebuild
            t = time.perf_counter()
            try:
                job, stamps, poses, closures, seconds = rebuild
                finished = job.step(REBUILD_STEP)
                seconds += time.perf_counter() - t
                rebuild = None if finished else (job, stamps, poses, closures, seconds)
                if finished:
                    send_maps(None, job, stamps, poses, closures, seconds)
            except Exception as exc:
                failed, rebuild = True, None
                report(exc)
            busy += time.perf_counter() - t
            continue
        msg = inbox.get()
        if msg is None:
            outbox.put(("stopped",))
            return
        if failed:
            continue
        t = time.perf_counter()
        try:
            if msg[0] == "key":
                if be.add(msg[1]):
                    dirty = True
                if be.closer.stats.checks:
                    loaded_now("check")
                busy += time.perf_counter() - t
                outbox.put(("done", len(be), be.latest(), busy))
                # rebuild the corrected maps when caught up, at most once per period (closures come in bursts)
                if (rebuild is None and dirty and _empty(inbox)
                        and time.monotonic() - last_rebuild >= settings.rebuild_period):
                    rebuild = start_rebuild(refresh=False)
            else:  # finish: the final maps, at once (a periodic rebuild in progress is superseded)
                job, stamps, poses, closures, _ = start_rebuild(refresh=True)
                job.step(len(stamps))
                rebuild = None
                send_maps(msg[1], job, stamps, poses, closures, time.perf_counter() - t)
                busy += time.perf_counter() - t
        except Exception as exc:
            failed = True
            report(exc)


def _empty(inbox) -> bool:
    try:
        return inbox.empty()
    except (OSError, NotImplementedError):
        return True


def _process_setup(parent_pid: int) -> None:
    """In the worker process: Ctrl-C is the runtime's to handle (it stops the worker), lower priority than
    the scans, one BLAS thread, and end when the runtime's process is gone (a SIGKILL runs no clean-up)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from runtime.tuning import background_priority, one_blas_thread

    background_priority()
    one_blas_thread()

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
