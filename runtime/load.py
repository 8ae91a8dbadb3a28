"""CPU-bound processes run beside a benchmark, so that figures "with N busy processes" are reproducible.

Each process is a separate Python interpreter spinning in a pure-Python loop (one core's worth of work,
no memory, no I/O); it ends when :class:`BusyProcesses` exits, and on its own if its parent dies (it polls
the parent's pid), so a killed benchmark leaves nothing behind.
"""

from __future__ import annotations

import os
import subprocess
import sys
from types import TracebackType

# a busy loop that checks every ~0.2 s whether the parent is still alive (then exits)
_SPIN = """
import os, sys, time
parent = int(sys.argv[1])
while True:
    end = time.monotonic() + 0.2
    while time.monotonic() < end:
        pass
    if os.getppid() != parent:
        sys.exit(0)
"""


class LoadError(ValueError):
    """A bad number of load processes."""


class BusyProcesses:
    """``with BusyProcesses(n):`` runs ``n`` CPU-bound processes (n >= 0) until the block ends."""

    def __init__(self, n: int) -> None:
        if n < 0:
            raise LoadError(f"the number of busy processes must be >= 0, got {n}")
        self.n = n
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "BusyProcesses":
        for _ in range(self.n):
            self.procs.append(subprocess.Popen([sys.executable, "-c", _SPIN, str(os.getpid())],
                                               stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL))
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def stop(self) -> None:
        """End the processes (idempotent)."""
        for p in self.procs:
            if p.poll() is None:
                p.kill()
        for p in self.procs:
            p.wait()
        self.procs.clear()

    @property
    def running(self) -> int:
        return sum(p.poll() is None for p in self.procs)
