"""Why a ``glassmap demo`` drops scans: the processing stage of a demo instrumented, per half second.

Runs the demo in this process (no recording unless --record) with the processing stage's queue and the
processor wrapped, and prints which counter dropped scans and when, how busy the processing thread was
in each half second (wall clock inside the processor, split by the kernel's schedstat into time on a core,
time waiting for a core, and the rest: waiting for the GIL or a lock), the largest gaps between scan
arrivals (the event loop or the emulated laser held up), and the garbage-collection pauses over 5 ms.

    python scripts/demo_drops.py [--speed 4] [--duration 40] [--queue N] [--record] [--world office]

docs/performance.md, "Round four (issue 19f)". Timings move with the machine's load: say it beside them.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's runtime, not an installed one


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--duration", type=float, default=None, help="emulated s (default: the whole route)")
    ap.add_argument("--queue", type=int, default=None, help="pipeline.queue_size before the demo scales it")
    ap.add_argument("--record", action="store_true", help="record MCAP as the default demo does")
    ap.add_argument("--world", default="office")
    ap.add_argument("--out", default="out/demo_drops")
    a = ap.parse_args(argv)

    from runtime.tuning import setup_process

    setup_process()
    import runtime.pipeline as P
    import runtime.processor as RP
    from runtime.config import RuntimeConfig
    from runtime.demo import DemoOptions, format_result, run_demo

    arrivals: list[tuple[float, int]] = []  # (host time, scans dropped from the full queue by this arrival)
    procs: list[tuple[float, float, float, float]] = []  # (start, wall, on a core, waiting for a core) s
    pauses: list[tuple[float, float, int, str]] = []  # gc: (start, s, generation, thread)
    submit, process = P.ProcessingStage.submit_scan, RP.MappingProcessor.process

    def submit_scan(self, scan, bytes_in_time=None):
        before = self.stats.dropped_overflow
        submit(self, scan, bytes_in_time)
        arrivals.append((time.monotonic(), self.stats.dropped_overflow - before))

    def timed_process(self, scan, odometry):
        t0, (c0, q0) = time.monotonic(), _schedstat()
        r = process(self, scan, odometry)
        c1, q1 = _schedstat()
        procs.append((t0, time.monotonic() - t0, c1 - c0, q1 - q0))
        return r

    gc_start: list[float] = [0.0]

    def on_gc(phase, info):
        if phase == "start":
            gc_start[0] = time.monotonic()
        elif time.monotonic() - gc_start[0] > 0.005:
            pauses.append((gc_start[0], time.monotonic() - gc_start[0], info["generation"],
                           threading.current_thread().name))

    P.ProcessingStage.submit_scan, RP.MappingProcessor.process = submit_scan, timed_process
    gc.callbacks.append(on_gc)
    cfg = RuntimeConfig()
    if a.queue is not None:
        cfg.pipeline.queue_size = a.queue
    opts = DemoOptions(world=a.world, speed=a.speed, duration=a.duration, out_dir=a.out, record=a.record,
                       progress=False, config=cfg)
    res = asyncio.run(run_demo(opts))
    print(format_result(res).split("\n")[0])
    print(res.summary.stages.summary(), f"(queue {cfg.pipeline.queue_size} scans at speed {a.speed:g}; "
          f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    if not arrivals:
        return 1
    t0 = arrivals[0][0]
    print("half-second windows: scans in / dropped from the full queue / processed; inside the processor: wall "
          "(busy fraction) = on a core + waiting for a core + the rest (GIL, locks), ms")
    end = max(t for t, _ in arrivals) - t0
    k = 0
    while k * 0.5 <= end:
        lo, hi = t0 + 0.5 * k, t0 + 0.5 * (k + 1)
        n_in = sum(1 for t, _ in arrivals if lo <= t < hi)
        n_drop = sum(d for t, d in arrivals if lo <= t < hi)
        ps = [p for p in procs if lo <= p[0] < hi]
        wall, cpu, queued = (sum(p[i] for p in ps) for i in (1, 2, 3))
        print(f"  {0.5 * k:6.1f} s  in {n_in:3d}  dropped {n_drop:3d}  processed {len(ps):3d}  "
              f"wall {1e3 * wall:5.0f} ({wall / 0.5:4.0%}) = {1e3 * cpu:4.0f} + {1e3 * queued:4.0f} + "
              f"{1e3 * (wall - cpu - queued):4.0f}")
        k += 1
    wall, cpu, queued = (sum(p[i] for p in procs) for i in (1, 2, 3))
    print(f"whole run, inside the processor: on a core {cpu / wall:.0%}, waiting for a core {queued / wall:.0%}, "
          f"the rest (GIL, locks) {(wall - cpu - queued) / wall:.0%} of {wall:.1f} s")
    gaps = sorted(((arrivals[i + 1][0] - arrivals[i][0], arrivals[i][0] - t0) for i in range(len(arrivals) - 1)),
                  reverse=True)[:5]
    print("largest gaps between scan arrivals:", ", ".join(f"{1e3 * g:.0f} ms at {t:.2f} s" for g, t in gaps))
    print("gc pauses > 5 ms:", ", ".join(f"{1e3 * d:.0f} ms (gen {g}, {th}) at {t - t0:.2f} s"
                                        for t, d, g, th in pauses) or "none")
    return 0


def _schedstat() -> tuple[float, float]:
    """(s on a core, s waiting for a core) of the calling thread (Linux schedstat; CPU time and 0 without)."""
    try:
        with open("/proc/thread-self/schedstat") as f:
            on_cpu, waiting, _ = f.read().split()
        return int(on_cpu) * 1e-9, int(waiting) * 1e-9
    except (OSError, ValueError):
        return time.thread_time(), 0.0


if __name__ == "__main__":
    sys.exit(main())
