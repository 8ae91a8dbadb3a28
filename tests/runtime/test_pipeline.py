"""The processing stage: bounded queue, stale-scan dropping with counters, odometry hand-over, crashes."""

from __future__ import annotations

import asyncio
import sys
import threading

import pytest

from runtime.config import PipelineConfig
from runtime.pipeline import ProcessingError, ProcessingStage, ScanResult
from tests.runtime.factories import make_odom, make_scan

pytestmark = pytest.mark.timeout(30)


class Recorder:
    """A processor that records its calls; optionally blocks until released (runs in the executor)."""

    def __init__(self, block: bool = False, fail_on: int | None = None) -> None:
        self.calls: list[tuple[int, list[float]]] = []
        self.release = threading.Event()
        self.started = threading.Event()
        if not block:
            self.release.set()
        self.fail_on = fail_on

    def process(self, scan, odometry):
        self.started.set()
        self.release.wait(10)
        if scan.seq == self.fail_on:
            raise ZeroDivisionError("boom")
        self.calls.append((scan.seq, [o.stamp for o in odometry]))
        return ScanResult(scan=scan, estimate=None, laser_pose=None, p_glass=None)


async def test_processes_in_order_with_the_odometry_that_arrived_before_each_scan():
    proc = Recorder()
    results = []
    stage = ProcessingStage(proc, queue_size=10, max_scan_age=1e9, on_result=results.append, clock=lambda: 0.0)
    stage.submit_odometry(make_odom(0.1))
    stage.submit_scan(make_scan(0.2, 1), bytes_in_time=0.25)
    stage.submit_odometry(make_odom(0.3))
    stage.submit_odometry(make_odom(0.4))
    stage.submit_scan(make_scan(0.45, 2))
    stage.close()
    await stage.run()
    assert proc.calls == [(1, [0.1]), (2, [0.3, 0.4])]
    assert [r.scan.seq for r in results] == [1, 2]
    assert results[0].bytes_in_time == 0.25
    assert stage.stats.scans_processed == 2 and stage.stats.dropped_overflow == stage.stats.dropped_stale == 0
    assert stage.stats.most_waiting == 2
    stage.shutdown()


async def test_default_queue_keeps_a_burst_of_five_scans_that_arrive_while_one_is_processed():
    """A link (or event loop) silent for 125 ms at 40 Hz then delivers five scans at once; the default queue
    keeps them all (the queue of 4 scans it replaced dropped the oldest)."""
    proc = Recorder(block=True)
    stage = ProcessingStage(proc, queue_size=PipelineConfig().queue_size, max_scan_age=1e9, clock=lambda: 0.0)
    runner = asyncio.create_task(stage.run())
    stage.submit_scan(make_scan(0.0, 0))
    await asyncio.get_running_loop().run_in_executor(None, proc.started.wait, 5)  # scan 0 is in the processor
    for seq in range(1, 6):
        stage.submit_scan(make_scan(0.025 * seq, seq))
    proc.release.set()
    stage.close()
    await runner
    assert [c[0] for c in proc.calls] == [0, 1, 2, 3, 4, 5]
    assert stage.stats.dropped_overflow == 0 and stage.stats.most_waiting == 5
    stage.shutdown()


async def test_full_queue_drops_oldest_and_counts_and_keeps_its_odometry():
    proc = Recorder(block=True)
    stage = ProcessingStage(proc, queue_size=2, max_scan_age=1e9, clock=lambda: 0.0)
    runner = asyncio.create_task(stage.run())
    stage.submit_scan(make_scan(0.0, 0))
    await asyncio.get_running_loop().run_in_executor(None, proc.started.wait, 5)  # scan 0 is in the processor
    for seq in range(1, 6):
        stage.submit_odometry(make_odom(float(seq)))
        stage.submit_scan(make_scan(float(seq), seq))
    assert stage.stats.dropped_overflow == 3 and stage.pending == 2
    assert stage.stats.most_waiting == 3  # the two queued and the one that found the queue full
    proc.release.set()
    stage.close()
    await runner
    assert [c[0] for c in proc.calls] == [0, 4, 5]
    assert proc.calls[1][1] == [1.0, 2.0, 3.0, 4.0]  # odometry of dropped scans 1..3 is not lost
    assert stage.stats.scans_received == 6 and stage.stats.scans_processed == 3
    stage.shutdown()


async def test_stale_scans_are_dropped_and_counted():
    proc = Recorder()
    now = [10.0]
    stage = ProcessingStage(proc, queue_size=10, max_scan_age=0.5, clock=lambda: now[0])
    stage.submit_odometry(make_odom(9.0))
    stage.submit_scan(make_scan(9.0, 1))  # 1 s old: stale
    stage.submit_scan(make_scan(9.8, 2))  # 0.2 s old: fresh
    stage.close()
    await stage.run()
    assert stage.stats.dropped_stale == 1
    assert proc.calls == [(2, [9.0])]
    stage.shutdown()


async def test_processor_crash_ends_the_stage_with_a_clear_error():
    stage = ProcessingStage(Recorder(fail_on=2), queue_size=10, max_scan_age=1e9, clock=lambda: 0.0)
    stage.submit_scan(make_scan(0.0, 1))
    stage.submit_scan(make_scan(0.1, 2))
    with pytest.raises(ProcessingError, match="scan 2.*ZeroDivisionError: boom"):
        await stage.run()
    stage.shutdown()


def test_bad_settings():
    with pytest.raises(ValueError):
        ProcessingStage(Recorder(), queue_size=0)
    with pytest.raises(ValueError):
        ProcessingStage(Recorder(), max_scan_age=0)
    with pytest.raises(ValueError):
        ProcessingStage(Recorder(), nice=-21)


@pytest.mark.parametrize("glass_scans", ["keys", "all"])
def test_processor_maps_occupancy_on_key_scans_and_glass_on_the_chosen_scans(glass_scans):
    """Standing still with keyframe_max_scans = 5: scans 0, 5, 10 are key scans; only they clear free space
    (the mapper's occupancy update); every scan gets a pose and p(glass) per beam; the glass map changes on the
    key scans only (glass_scans = keys) or on every scan (all)."""
    import numpy as np

    from glassmap.types import Odometry, Scan
    from runtime.config import MappingConfig
    from runtime.processor import MappingProcessor
    from tests.pose.synth import make_scan as room_scan, room_with_corner

    proc = MappingProcessor(MappingConfig(laser_x=0.0, initial_x=-1.5, initial_y=-1.0, keyframe_max_scans=5,
                                          glass_scans=glass_scans))
    segs = room_with_corner()
    rng = np.random.default_rng(0)
    cleared, keys, glass_changed = [], [], []  # per scan: free space cleared? glass map changed?
    before = glass_before = None
    for k in range(12):
        s = room_scan(segs, np.array([-1.5, -1.0, 0.0]), stamp=0.025 * k, noise=0.01, rng=rng)
        scan = Scan(stamp=s.stamp, ranges=s.ranges, intensities=np.full(s.ranges.shape, 3000.0),
                    geometry=s.geometry, seq=k)
        res = proc.process(scan, [Odometry(stamp=0.025 * k, x=0.0, y=0.0, yaw=0.0)])
        assert res.estimate is not None and np.isfinite(res.p_glass).any()
        keys.append(proc.estimator.stats.last_keyframe)
        lo = proc.mapper.occupancy.log_odds.copy()
        cleared.append(before is not None and lo.shape == before.shape and bool((lo < before - 1e-9).any()))
        before = lo
        glass = proc.mapper.grid[proc.mapper.config.layer].copy()
        glass_changed.append(glass_before is None or glass.shape != glass_before.shape
                             or not np.array_equal(glass, glass_before))
        glass_before = glass
    assert np.flatnonzero(keys).tolist() == [0, 5, 10]
    # (beams classified as glass may raise cells on a glass-map update: glass_hits_occupy; only key scans clear)
    assert np.flatnonzero(cleared).tolist() == [5, 10]
    assert np.flatnonzero(glass_changed).tolist() == ([0, 5, 10] if glass_scans == "keys" else list(range(12)))
    assert proc.estimator.stats.scans == 12


async def test_a_failing_result_handler_ends_the_stage_with_its_error():
    proc = Recorder()

    def on_result(r):
        if r.scan.seq == 2:
            raise KeyError("sink broken")

    stage = ProcessingStage(proc, queue_size=10, max_scan_age=1e9, on_result=on_result, clock=lambda: 0.0)
    for seq in range(1, 6):
        stage.submit_scan(make_scan(0.1 * seq, seq))
    with pytest.raises(KeyError, match="sink broken"):
        await stage.run()
    stage.shutdown()


async def test_calls_run_between_scans_and_before_the_queued_ones():
    """A call (map copy, warm-up) never overlaps a scan, and goes before scans still waiting."""
    log: list[str] = []
    busy = threading.Lock()

    class Tracing(Recorder):
        def process(self, scan, odometry):
            assert busy.acquire(blocking=False), "a call overlapped a scan"
            try:
                r = super().process(scan, odometry)
                log.append(f"scan {scan.seq}")
                return r
            finally:
                busy.release()

    def call():
        assert busy.acquire(blocking=False), "a scan overlapped a call"
        log.append("call")
        busy.release()

    proc = Tracing(block=True)
    stage = ProcessingStage(proc, queue_size=10, max_scan_age=1e9, clock=lambda: 0.0)
    runner = asyncio.create_task(stage.run())
    stage.submit_scan(make_scan(0.0, 0))
    await asyncio.get_running_loop().run_in_executor(None, proc.started.wait, 5)  # scan 0 is in the processor
    stage.submit_scan(make_scan(0.1, 1))
    stage.submit_scan(make_scan(0.2, 2))
    pending_call = asyncio.create_task(stage.call(call))
    while not stage._calls_waiting:  # the call is waiting for scan 0 to end
        await asyncio.sleep(0.005)
    proc.release.set()
    await pending_call
    stage.close()
    await runner
    assert log == ["scan 0", "call", "scan 1", "scan 2"]
    stage.shutdown()


class NicenessProbe(Recorder):
    """A processor that notes the niceness of the thread it runs in (Linux: each thread has its own)."""

    def process(self, scan, odometry):
        import os

        self.niceness = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return super().process(scan, odometry)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own priority is Linux only")
async def test_the_processing_thread_runs_at_the_niceness_asked_for():
    import os

    base = os.getpriority(os.PRIO_PROCESS, 0)
    proc = NicenessProbe()
    stage = ProcessingStage(proc, max_scan_age=1e9, clock=lambda: 0.0, nice=min(base + 3, 19))
    stage.submit_scan(make_scan(0.0, 0))
    stage.close()
    await stage.run()
    stage.shutdown()
    assert proc.niceness == min(base + 3, 19)
    assert os.getpriority(os.PRIO_PROCESS, 0) == base  # the rest of the process is not touched


async def test_a_refused_niceness_is_a_warning_and_the_scans_still_run(monkeypatch, caplog):
    import os

    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    monkeypatch.setattr(sys, "platform", "linux")
    proc = Recorder()
    stage = ProcessingStage(proc, max_scan_age=1e9, clock=lambda: 0.0, nice=-5)
    stage.submit_scan(make_scan(0.0, 0))
    stage.close()
    with caplog.at_level("WARNING", logger="runtime.tuning"):
        await stage.run()
    stage.shutdown()
    assert [c[0] for c in proc.calls] == [0]
    assert any("pipeline.nice -5 refused" in r.getMessage() and "ulimit -e" in r.getMessage() for r in caplog.records)
