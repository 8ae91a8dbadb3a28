"""The processing stage: a bounded scan queue in front of one processing thread.

Scans come from the laser task (:meth:`ProcessingStage.submit_scan`, never blocks), odometry from the base
task (:meth:`ProcessingStage.submit_odometry`). Each scan is processed with the odometry that arrived
before it (arrival order, not processing time), so a replay of the recording in file order feeds the
processor exactly what the live run fed it; the odometry of a dropped scan goes to the next one. The
processing thread takes the scans off the queue itself and hands each result back to the event loop, so a
busy event loop (a burst of scans to decode, odometry, the driver) never holds up the next scan. Scans are
never dropped silently: when the queue is full the oldest waiting scan is dropped (``dropped_overflow``); a
scan older than ``max_scan_age`` seconds (host clock) when its turn comes is dropped (``dropped_stale``).
An exception in the processor ends :meth:`ProcessingStage.run` with :class:`ProcessingError` (the runtime
then stops the robot).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from glassmap.types import Odometry, PoseEstimate, Scan
from runtime.tuning import thread_priority

log = logging.getLogger(__name__)


class ProcessingError(RuntimeError):
    """The per-scan processing failed; the message names the scan and the cause."""


@dataclass
class ScanResult:
    """What the processing of one scan produced (map frame; times in host seconds)."""

    scan: Scan
    estimate: PoseEstimate | None
    laser_pose: np.ndarray | None  # (3,) laser pose in the map frame
    p_glass: np.ndarray | None  # (n,) per-beam p(glass), NaN where no angle
    odom: Odometry | None = None  # the latest odometry at or before the scan (for map -> odom)
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    bytes_in_time: float | None = None  # host time the scan's last bytes arrived
    done_time: float = 0.0  # host time the maps were updated
    corrected_pose: PoseEstimate | None = None  # the estimate corrected by the pose graph (mapping.loop_closure)


class ScanProcessor(Protocol):
    """The heavy work for one scan, run in the processing thread (one at a time)."""

    def process(self, scan: Scan, odometry: list[Odometry]) -> ScanResult: ...


@dataclass
class StageStats:
    scans_received: int = 0
    scans_processed: int = 0
    dropped_overflow: int = 0
    dropped_stale: int = 0
    odometry_received: int = 0
    odometry_dropped: int = 0
    busy_time: float = 0.0  # seconds spent in the processor
    most_waiting: int = 0  # the most scans waiting at once, counting one that arrived to a full queue

    def summary(self) -> str:
        return (f"scans received {self.scans_received}, processed {self.scans_processed}, "
                f"dropped: queue full {self.dropped_overflow}, stale {self.dropped_stale}; "
                f"odometry messages {self.odometry_received}")


class ProcessingStage:
    """Bounded queue + processing thread between the device tasks and the processor.

    :meth:`run` starts the processing thread and returns when it ends; :meth:`call` runs other work on
    the processor (map copies, the warm-up) between two scans, before, during or after :meth:`run`."""

    def __init__(self, processor: ScanProcessor, *, queue_size: int = 8, max_scan_age: float = 0.5,
                 odom_buffer: int = 400, on_result: Callable[[ScanResult], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, nice: int = 0) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        if max_scan_age <= 0:
            raise ValueError("max_scan_age must be > 0")
        if not -20 <= nice <= 19:
            raise ValueError("nice must be in -20 .. 19")
        self.processor = processor
        self.queue_size = queue_size
        self.max_scan_age = max_scan_age
        self.nice = nice
        self.on_result = on_result
        self.clock = clock
        self.stats = StageStats()
        self._scans: deque[tuple[Scan, float | None, list[Odometry]]] = deque()
        self._odom: deque[Odometry] = deque(maxlen=odom_buffer)
        self._carry: list[Odometry] = []  # odometry of dropped scans, for the next processed one
        self._cond = threading.Condition()  # guards _scans, _closed, _abandon, _calls_waiting
        self._closed = False
        self._abandon = False  # stop after the current scan, leaving the queue (run() cancelled, shutdown)
        self._calls_waiting = 0  # call()s waiting for the processor: they go before the next scan
        self._busy = threading.Lock()  # held while the processor works (a scan or a call)
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None  # runs call()s

    # -- producers (event loop thread) -------------------------------------------------------------------
    def submit_scan(self, scan: Scan, bytes_in_time: float | None = None) -> None:
        self.stats.scans_received += 1
        odoms = list(self._odom)
        self._odom.clear()
        with self._cond:
            self.stats.most_waiting = max(self.stats.most_waiting, len(self._scans) + 1)
            if len(self._scans) >= self.queue_size:
                old, _, old_odoms = self._scans.popleft()
                self.stats.dropped_overflow += 1
                log.debug("scan %d dropped: processing queue full", old.seq)
                if self._scans:
                    nxt = self._scans[0]
                    self._scans[0] = (nxt[0], nxt[1], old_odoms + nxt[2])
                else:
                    odoms = old_odoms + odoms
            self._scans.append((scan, bytes_in_time, odoms))
            self._cond.notify()

    def submit_odometry(self, odom: Odometry) -> None:
        self.stats.odometry_received += 1
        if len(self._odom) == self._odom.maxlen:
            self.stats.odometry_dropped += 1
        self._odom.append(odom)

    def close(self) -> None:
        """Let :meth:`run` finish the queued scans and return."""
        with self._cond:
            self._closed = True
            self._cond.notify()

    @property
    def pending(self) -> int:
        return len(self._scans)

    # -- consumer ------------------------------------------------------------------------------------------
    async def run(self) -> None:
        """Process the queued scans in the processing thread until :meth:`close` (then the queue is emptied)
        or the processor fails (:class:`ProcessingError`). Results go to ``on_result`` on this event loop,
        in order, before this returns. Cancelled: the thread stops after its current scan."""
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        worker = threading.Thread(target=self._work, args=(loop, done), name="glassmap-proc", daemon=True)
        worker.start()
        try:
            await done
        except asyncio.CancelledError:
            self._stop_thread()
            raise

    def _work(self, loop: asyncio.AbstractEventLoop, done: asyncio.Future) -> None:
        """The processing thread: take the oldest scan, drop it if stale, process it, hand the result over."""
        error: BaseException | None = None
        if self.nice:
            thread_priority(self.nice)
        while True:
            with self._cond:
                while not self._abandon and (self._calls_waiting or (not self._scans and not self._closed)):
                    self._cond.wait()
                if self._abandon or not self._scans:
                    break
                scan, t_in, odoms = self._scans.popleft()
            odoms = self._carry + odoms
            self._carry = []
            age = self.clock() - scan.stamp
            if age > self.max_scan_age:
                self.stats.dropped_stale += 1
                self._carry = odoms
                log.debug("scan %d dropped: stale (%.3f s old)", scan.seq, age)
                continue
            t0 = time.perf_counter()
            try:
                with self._busy:
                    result = self.processor.process(scan, odoms)
            except Exception as exc:
                error = ProcessingError(f"processing scan {scan.seq} (t={scan.stamp:.3f}) failed: "
                                        f"{type(exc).__name__}: {exc}")
                error.__cause__ = exc
                break
            self.stats.busy_time += time.perf_counter() - t0
            self.stats.scans_processed += 1
            result.bytes_in_time = t_in
            result.done_time = self.clock()
            if not _call_soon(loop, self._deliver, result, done):
                return
        _call_soon(loop, _settle, done, error)

    def _deliver(self, result: ScanResult, done: asyncio.Future) -> None:
        """``on_result`` on the event loop; if it raises, :meth:`run` raises that and the thread stops."""
        if self.on_result is None or done.done():
            return
        try:
            self.on_result(result)
        except Exception as exc:
            self._stop_thread()
            done.set_exception(exc)

    def _stop_thread(self) -> None:
        with self._cond:
            self._abandon = True
            self._cond.notify()

    def shutdown(self) -> None:
        """Stop the processing thread after its current scan and release the thread that runs calls."""
        self._stop_thread()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)

    async def call(self, fn, *args):
        """Run ``fn(*args)`` on the processor between two scans (never during one: safe for the maps), in a
        thread of its own; it goes before the scans still queued."""
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="glassmap-call")
        return await asyncio.get_running_loop().run_in_executor(self._executor, self._call, fn, args)

    def _call(self, fn, args):
        with self._cond:  # the processing thread waits for it before taking its next scan
            self._calls_waiting += 1
        try:
            with self._busy:
                return fn(*args)
        finally:
            with self._cond:
                self._calls_waiting -= 1
                self._cond.notify()


def _call_soon(loop: asyncio.AbstractEventLoop, fn, *args) -> bool:
    """``loop.call_soon_threadsafe``; False if the loop is closed (nobody waits for the result any more)."""
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        return False
    return True


def _settle(fut: asyncio.Future, error: BaseException | None) -> None:
    if fut.done():
        return
    if error is None:
        fut.set_result(None)
    else:
        fut.set_exception(error)
