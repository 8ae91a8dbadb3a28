"""Per-stage CPU time of the scan processing (``glassmap bench --stages``): where a scan's time goes.

:func:`stage_profile` replays a recording as fast as possible with the functions of :data:`STAGES` wrapped
to add up the CPU time of the calling thread (``time.thread_time``: other processes and threads do not
inflate it, so the figures hold on a shared machine) and their calls. Stages nest (the table shows them
indented under their parent); each figure is inclusive of the stages below it. The wrappers cost ~1 us a
call, so the processing's total is a little higher than in a plain replay. The CPU time of the whole process
from the first scan to the last, per scan (and as a rate: scans per second of CPU time; what two threads on
two cores spend on each other is in it, so a replay pinned to one core, ``glassmap bench``, can be faster),
is split into the processing (the stages and the replay loop), reading and decoding the recording (in the
same thread, between scans: each item taken from the source, timed by the thread's clock) and the rest
(other threads: the likelihood-field worker).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

# (depth, label, module, attribute path): the functions timed, in the order and nesting of the table
STAGES: tuple[tuple[int, str, str, str], ...] = (
    (0, "whole scan (MappingProcessor.process)", "runtime.processor", "MappingProcessor.process"),
    (1, "pose: prediction + key-scan matching + fusion", "glassmap.pose.estimator", "PoseEstimator.update"),
    (2, "scan matching (key scans)", "glassmap.pose.matcher", "CorrelativeMatcher.match"),
    (2, "likelihood field rebuild", "glassmap.pose.estimator", "PoseEstimator._rebuild_field"),
    (2, "likelihood field update (key scans)", "glassmap.pose.estimator", "PoseEstimator._update_field"),
    (1, "registration sigma per beam", "glassmap.pose.estimator", "PoseEstimator.registration_sigma"),
    (1, "glass path (GlassMapper.process)", "glassmap.mapping", "GlassMapper.process"),
    (2, "incidence angles (split-merge)", "glassmap.mapping", "incidence_angles"),
    (2, "classifier features", "glassmap.classifier", "scan_features"),
    (2, "classifier network", "glassmap.classifier", "GlassClassifier._logits"),
    (2, "occupancy update (key scans)", "glassmap.mapping", "GlassMapper.integrate"),
    (2, "glass hits", "glassmap.mapping", "GlassMapper.mark_glass_hits"),
    (2, "registration + glass-map update", "glassmap.mapping", "GlassMapper.register"),
)


@dataclass
class StageTimes:
    """CPU seconds and calls per stage label, and the scans and process CPU time of the replay."""

    cpu: dict[str, float] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)
    scans: int = 0
    process_cpu: float = 0.0  # all threads of this process from the first scan to the last (reading, decoding, ...)
    processing_cpu: float = 0.0  # the replaying thread over the same span, reading excluded (stages, replay loop)
    reader_cpu: float = 0.0  # reading and decoding the recording over the same span (the replaying thread)
    wall: float = 0.0
    span: list[float] = field(default_factory=list)  # process CPU time at the first scan's start, the last one's end
    thread_span: list[float] = field(default_factory=list)  # the same, CPU time of the replaying thread
    reading: list[float] = field(default_factory=lambda: [0.0, 0.0])  # reading CPU so far, and at the last scan's end

    def table(self) -> str:
        """Markdown table: stage, calls, mean CPU ms per scan, share of the whole scan."""
        n = max(self.scans, 1)
        whole = self.cpu.get(STAGES[0][1], 0.0)
        rows = ["| stage | calls | CPU ms per scan (mean) | share |", "|---|---|---|---|"]
        for depth, label, _, _ in STAGES:
            t = self.cpu.get(label, 0.0)
            share = f"{100 * t / whole:.0f} %" if whole > 0 else ""
            indent = "&nbsp;" * 4 * depth
            rows.append(f"| {indent}{label} | {self.calls.get(label, 0)} | {1e3 * t / n:.3f} | {share} |")
        rows.append(f"| all threads of the process from the first scan to the last (reading, decoding, processing) | | "
                    f"{1e3 * self.process_cpu / n:.3f} | |")
        rest = self.process_cpu - self.processing_cpu - self.reader_cpu
        for label, t in (("processing (the stages above, the replay loop)", self.processing_cpu),
                         ("reading and decoding the recording (same thread, between scans)", self.reader_cpu),
                         ("other threads (likelihood-field worker, ...)", rest)):
            rows.append(f"| {'&nbsp;' * 4}{label} | | {1e3 * t / n:.3f} | |")
        if self.process_cpu > 0:
            rows.append(f"| the same as a rate: scans per second of CPU time (all threads) | | {n / self.process_cpu:.0f} | |")
        return "\n".join(rows)


def _resolve(module: str, path: str):
    owner = importlib.import_module(module)
    *outer, name = path.split(".")
    for part in outer:
        owner = getattr(owner, part)
    return owner, name


@contextlib.contextmanager
def timed_stages(times: StageTimes) -> Iterator[StageTimes]:
    """Wrap the functions of :data:`STAGES` for the duration of the block (re-entrant calls count once;
    the stages below the whole scan count only inside a scan, not in a warm-up)."""
    patched = []
    scan = [0]  # whole-scan calls in progress
    try:
        for _, label, module, path in STAGES:
            owner, name = _resolve(module, path)
            fn = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
            times.cpu.setdefault(label, 0.0)
            times.calls.setdefault(label, 0)
            setattr(owner, name, _timed(fn, label, times, scan))
            patched.append((owner, name, fn))
        yield times
    finally:
        for owner, name, fn in reversed(patched):
            setattr(owner, name, fn)


def _timed(fn, label: str, times: StageTimes, scan: list[int]):
    depth = [0]
    top = label == STAGES[0][1]

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if depth[0] or not (top or scan[0]):
            return fn(*args, **kwargs)
        depth[0] += 1
        if top:
            scan[0] += 1
            if not times.span:
                times.span[:] = [time.process_time()] * 2
                times.thread_span[:] = [time.thread_time()] * 2
        t = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            t1 = time.thread_time()
            times.cpu[label] += t1 - t
            times.calls[label] += 1
            depth[0] -= 1
            if top:
                scan[0] -= 1
                times.span[1] = time.process_time()
                times.thread_span[1] = t1
                times.reading[1] = times.reading[0]
    return wrapper


def stage_profile(recording: str, source: str = "messages") -> StageTimes:
    """Replay ``recording`` (all its scans, as fast as possible) with the stages timed."""
    from runtime import replay

    times = StageTimes()
    source_items = replay.iter_source

    def timed_source(*args, **kwargs):  # reading and decoding, timed once the first scan has started
        items = iter(source_items(*args, **kwargs))
        while True:
            t = time.thread_time()
            try:
                item = next(items)
            except StopIteration:
                return
            finally:
                if times.span:
                    times.reading[0] += time.thread_time() - t
            yield item

    replay.iter_source = timed_source
    try:
        with timed_stages(times):
            r = replay.replay_file(recording, source=source, as_recorded=False, progress=False)
    finally:
        replay.iter_source = source_items
    times.process_cpu = times.span[1] - times.span[0] if times.span else 0.0
    thread_cpu = times.thread_span[1] - times.thread_span[0] if times.thread_span else 0.0
    times.reader_cpu = times.reading[1]
    times.processing_cpu = thread_cpu - times.reader_cpu
    times.scans, times.wall = r.scans, r.wall_time
    return times
