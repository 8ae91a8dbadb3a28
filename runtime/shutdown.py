"""Clean shutdown: SIGINT (Ctrl-C) and SIGTERM set a stop event instead of killing the program.

The first signal asks the runtime to stop (laser stopped, robot stopped and disabled, recording finished);
a second one within the grace period raises KeyboardInterrupt in the event loop as a last resort.
"""

from __future__ import annotations

import asyncio
import logging
import signal
from contextlib import contextmanager

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """An asyncio event set by SIGINT/SIGTERM (or by code: :meth:`set`), with the reason."""

    def __init__(self) -> None:
        self.event = asyncio.Event()
        self.reason = ""
        self._count = 0

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            log.warning("stopping: %s", reason)
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    async def wait(self) -> None:
        await self.event.wait()

    def _on_signal(self, signum: int) -> None:
        self._count += 1
        name = signal.Signals(signum).name
        if self._count == 1:
            self.set(f"{name} received")
        else:
            log.error("%s received again: aborting now", name)
            raise KeyboardInterrupt


@contextmanager
def handle_signals(stop: StopRequest):
    """Route SIGINT and SIGTERM to ``stop`` while the block runs (must run inside the event loop thread)."""
    loop = asyncio.get_running_loop()
    installed = []
    for sig in SIGNALS:
        try:
            loop.add_signal_handler(sig, stop._on_signal, sig)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):  # not the main thread
            pass
    try:
        yield stop
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
