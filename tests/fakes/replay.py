"""Replay a recorded capture as the device: over a real pseudo-terminal or a loopback TCP socket.

The replayer plays the device's side of the capture. For each recorded ``tx`` chunk (host -> device) it
waits until the host has sent that many bytes (and counts mismatches); for each ``rx`` chunk it writes the
recorded bytes, at the original relative time (``realtime=True``) or as fast as possible.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

from drivers.capture import Capture
from drivers.endpoints import PtyEndpoint, serve_pty, serve_tcp


@dataclass
class ReplayStats:
    rx_written: int = 0
    tx_expected: int = 0
    tx_received: bytearray = field(default_factory=bytearray)
    tx_mismatches: int = 0
    finished: bool = False


class CaptureReplayer:
    """Plays one capture to one connection. Use :func:`replay_over_pty` or :func:`replay_over_tcp`."""

    def __init__(self, capture: Capture, *, realtime: bool = False, tx_timeout: float = 5.0,
                 hold_open: bool = True) -> None:
        self.capture = capture
        self.realtime = realtime
        self.tx_timeout = tx_timeout
        self.hold_open = hold_open
        self.stats = ReplayStats()
        self.done = asyncio.Event()

    async def __call__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        t0 = time.monotonic()
        pending = bytearray()
        try:
            for chunk in self.capture.chunks:
                if chunk.direction == "tx":
                    self.stats.tx_expected += len(chunk.data)
                    while len(pending) < len(chunk.data):
                        more = await asyncio.wait_for(reader.read(65536), self.tx_timeout)
                        if not more:
                            return
                        pending += more
                        self.stats.tx_received += more
                    got, pending = bytes(pending[: len(chunk.data)]), pending[len(chunk.data):]
                    if got != chunk.data:
                        self.stats.tx_mismatches += 1
                else:
                    if self.realtime:
                        delay = t0 + chunk.t - time.monotonic()
                        if delay > 0:
                            await asyncio.sleep(delay)
                    writer.write(chunk.data)
                    await writer.drain()
                    self.stats.rx_written += len(chunk.data)
            self.stats.finished = True
            self.done.set()
            if self.hold_open:  # keep the link up (a real device does not hang up) and keep listening
                while more := await reader.read(65536):
                    self.stats.tx_received += more
        except (asyncio.TimeoutError, ConnectionError, OSError):
            pass
        finally:
            self.done.set()


async def replay_over_pty(capture: Capture, **kwargs) -> tuple[str, CaptureReplayer, PtyEndpoint, asyncio.Task]:
    """Start replaying on a new pty; returns (path for the host to open, replayer, endpoint, task)."""
    endpoint = PtyEndpoint()
    replayer = CaptureReplayer(capture, **kwargs)
    task = await serve_pty(replayer, endpoint)
    return endpoint.path, replayer, endpoint, task


async def replay_over_tcp(capture: Capture, **kwargs) -> tuple[str, CaptureReplayer, asyncio.base_events.Server]:
    """Start a loopback TCP server replaying to its first client; returns (tcp:// URL, replayer, server)."""
    replayer = CaptureReplayer(capture, **kwargs)
    server = await serve_tcp(replayer)
    port = server.sockets[0].getsockname()[1]
    return f"tcp://127.0.0.1:{port}", replayer, server


def feed_capture(capture: Capture, session) -> list:
    """Feed a capture to a receive session in recorded order (``tx`` what was sent, ``rx`` what came back, each
    with its recorded host time); returns everything the ``rx`` calls yielded."""
    out = []
    for c in capture.chunks:
        if c.direction == "tx":
            session.tx(c.t, c.data)
        else:
            out.extend(session.rx(c.t, c.data))
    return out
