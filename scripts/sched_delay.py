"""Run a glassmap command with the processing of every scan timed from the kernel's scheduler statistics, and
print where each scan's wall-clock time went: its thread on a CPU, waiting for a CPU (runnable but not
running: the run queue), and blocked (waiting for the GIL or a lock). Linux only
(/proc/thread-self/schedstat).

Usage: python scripts/sched_delay.py [--scans N] glassmap bench --world W --duration 60 --load 1 --pinned-runs 0

Only the first N processed scans count (default 2400: the live run of ``glassmap bench --duration 60``; the
replays that follow it are left out).
"""

from __future__ import annotations

import sys
import time

import numpy as np


def _schedstat() -> tuple[float, float]:
    """(seconds on a CPU, seconds runnable but waiting for one) of the calling thread so far."""
    with open("/proc/thread-self/schedstat") as f:
        on_cpu, waiting, _ = f.read().split()
    return int(on_cpu) * 1e-9, int(waiting) * 1e-9


def main() -> int:
    args = sys.argv[1:]
    limit = 2400
    if args[:1] == ["--scans"]:
        limit, args = int(args[1]), args[2:]
    if args[:1] != ["glassmap"]:
        print(__doc__, file=sys.stderr)
        return 2
    import runtime.processor as processor

    rows: list[tuple[float, float, float, bool]] = []  # wall, on CPU, waiting for a CPU (s), key scan
    process = processor.MappingProcessor.process

    def timed(self, scan, odometry):
        c0, w0 = _schedstat()
        t0 = time.perf_counter()
        result = process(self, scan, odometry)
        c1, w1 = _schedstat()
        if len(rows) < limit:
            rows.append((time.perf_counter() - t0, c1 - c0, w1 - w0, bool(self.estimator.stats.last_keyframe)))
        return result

    processor.MappingProcessor.process = timed
    from runtime.cli import main as glassmap

    sys.argv = args
    try:
        code = glassmap()
    finally:
        report(np.array(rows, dtype=float).reshape(-1, 4))
    return code or 0


def report(a: np.ndarray) -> None:
    if not a.size:
        print("sched_delay: no scans processed")
        return
    a = a.copy()
    key = a[:, 3] > 0
    a[:, :3] *= 1e3
    print(f"sched_delay: {a.shape[0]} scans ({int(key.sum())} key scans); ms per scan in the processing thread")
    for name, sel in (("all scans", slice(None)), ("key scans", key)):
        wall, cpu, wait = a[sel, 0], a[sel, 1], a[sel, 2]
        if not wall.size:
            continue
        blocked = wall - cpu - wait
        for q in (50, 90, 99):
            print(f"  {name:9s} p{q}: wall {np.percentile(wall, q):6.2f}  on a CPU {np.percentile(cpu, q):6.2f}  "
                  f"waiting for a CPU {np.percentile(wait, q):6.2f}  blocked {np.percentile(blocked, q):6.2f}")
    worst = np.argsort(a[:, 0])[-max(1, a.shape[0] // 100):]  # the slowest 1 %
    w = a[worst]
    print(f"  slowest 1 % ({worst.size} scans), mean: wall {w[:, 0].mean():.2f} = on a CPU {w[:, 1].mean():.2f} + "
          f"waiting for a CPU {w[:, 2].mean():.2f} + blocked {(w[:, 0] - w[:, 1] - w[:, 2]).mean():.2f}")


if __name__ == "__main__":
    sys.exit(main())
