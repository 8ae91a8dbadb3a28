"""The pose-graph worker: runs the SLAM back end in its own thread, off the 40 Hz scan path.

The processing thread hands over each key scan (:meth:`GraphWorker.submit`, never blocks; the estimator's
``last_key_scan`` with the raw scan and its p(glass)); the worker adds it to the
:class:`~glassmap.pose.backend.GraphBackEnd` (iSAM2, submaps, loop-closure checks). After accepted loop
closures (once it has caught up with the queue, at most every ``rebuild_period`` s) and when asked at the
end of a run, it re-integrates the key scans at the optimised poses into a corrected occupancy grid and,
when the key scans carry p(glass), a corrected glass map (:func:`glassmap.pose.corrected.rebuild_maps`).
Readers take snapshots under a lock: the latest correction (front-end frame -> corrected frame), the
optimised trajectory and the corrected maps. The queue is not bounded and every key scan is processed in
order, so a replay of a recording reproduces the final graph exactly.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from glassmap.grid import OccupancyGrid, OccupancyParams
from glassmap.mapping import GlassMapper, MapperConfig
from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from glassmap.pose.keyscan import KeyScan

log = logging.getLogger(__name__)


@dataclass
class GraphSnapshot:
    """What the worker has published: stamps (N,) s and poses (N, 3) of the optimised key scans (map
    frame), the number of accepted loop closures, the corrected grid and glass mapper (None before the first
    closure or :meth:`GraphWorker.finish`; the mapper also without a mapper config), and ``version``
    (incremented on every new corrected map)."""

    stamps: np.ndarray
    poses: np.ndarray
    closures: int
    grid: OccupancyGrid | None
    version: int
    glass: GlassMapper | None = None


class GraphWorker:
    """A :class:`GraphBackEnd` in a daemon thread (see the module docstring)."""

    def __init__(self, config: BackEndConfig = BackEndConfig(), sigma_hit: float = 0.03,
                 occupancy: OccupancyParams = OccupancyParams(), resolution: float = 0.05,
                 mapper: MapperConfig | None = None, classifier=None, rebuild_period: float = 5.0) -> None:
        self.backend = GraphBackEnd(config, sigma_hit)
        self.occupancy = occupancy
        self.resolution = resolution
        self.mapper, self.classifier = mapper, classifier
        self.rebuild_period = rebuild_period  # s: at most one corrected-map rebuild per period
        self._dirty = False  # a closure moved the graph since the last corrected map
        self._last_rebuild = -float("inf")
        self._queue: queue.SimpleQueue[KeyScan | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._correction = np.zeros(3)
        self._snapshot = GraphSnapshot(np.zeros(0), np.zeros((0, 3)), 0, None, 0)
        self._pending = 0
        self._idle = threading.Condition()
        self.busy_time = 0.0  # s spent in the back end
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="pose-graph", daemon=True)
        self._thread.start()

    def submit(self, key: KeyScan) -> None:
        """Queue one key scan (from the processing thread; returns at once)."""
        with self._idle:
            self._pending += 1
        self._queue.put(key)

    def correction(self) -> np.ndarray:
        """(3,) the latest correction: compose(correction, front-end pose) = corrected pose."""
        with self._lock:
            return self._correction.copy()

    def snapshot(self) -> GraphSnapshot:
        with self._lock:
            return self._snapshot

    def finish(self, timeout: float = 60.0) -> GraphSnapshot:
        """Wait until every submitted key scan is in the graph, build the corrected grid at the final
        solution, and return the snapshot. Raises TimeoutError if the worker does not catch up in time."""
        deadline = time.monotonic() + timeout
        with self._idle:
            while self._pending and self.error is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"the pose-graph worker still has {self._pending} key scans after {timeout} s")
                self._idle.wait(left)
        if self.error is not None:
            raise RuntimeError(f"the pose-graph worker failed: {self.error}") from self.error
        self._publish(grid=True)
        return self.snapshot()

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=5.0)

    def _publish(self, grid: bool) -> None:
        be = self.backend
        self._dirty, self._last_rebuild = False, time.monotonic()
        poses = be.poses()
        occ = gm = None
        if grid and len(be):
            occ, gm = be.corrected_maps(self.occupancy, self.resolution, poses, self.mapper, self.classifier)
        with self._lock:
            old = self._snapshot
            self._snapshot = GraphSnapshot(be.stamps(), poses, len(be.closures), occ if grid else old.grid,
                                           old.version + int(grid), gm if grid else old.glass)

    def _run(self) -> None:
        while True:
            key = self._queue.get()
            if key is None:
                return
            t = time.perf_counter()
            try:
                closures = self.backend.add(key)
                corr = self.backend.correction()
                with self._lock:
                    self._correction = corr
                if closures:
                    log.info("loop closure at t=%.2f: %d accepted (%d in all)", key.stamp, len(closures),
                             len(self.backend.closures))
                    self._dirty = True
                # rebuild the corrected maps when caught up, at most once per period (closures come in bursts)
                if self._dirty and self._queue.empty() and time.monotonic() - self._last_rebuild >= self.rebuild_period:
                    self._publish(grid=True)
            except Exception as exc:  # reported by finish(); the scans go on without the back end
                log.error("pose-graph worker stopped: %s: %s", type(exc).__name__, exc)
                self.error = exc
            finally:
                self.busy_time += time.perf_counter() - t
                with self._idle:
                    self._pending -= 1
                    self._idle.notify_all()
            if self.error is not None:
                with self._idle:  # drain: nothing more will be processed
                    while not self._queue.empty():
                        self._queue.get()
                        self._pending -= 1
                    self._idle.notify_all()
                return
