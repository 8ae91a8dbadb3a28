"""The device side of a link, for emulators and replayers: pseudo-terminals and loopback TCP servers.

Both hand a connection to the device code as an asyncio ``(StreamReader, StreamWriter)`` pair, so one
device implementation serves a pty and a socket alike. Servers bind to 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
import termios
import tty
from collections.abc import Awaitable, Callable

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


_SPEED_CONST = {b: getattr(termios, f"B{b}") for b in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200,
                                                      230400, 460800, 500000, 576000, 921600)}
_SPEED_BAUD = {c: b for b, c in _SPEED_CONST.items()}


class PtyEndpoint:
    """A pseudo-terminal pair in raw mode; the host opens ``path`` (a stable symlink) as a serial port.

    ``hangup()`` closes the current pair (the host sees the link drop) and ``reopen()`` makes a new pair
    behind the same ``path``, like a USB device re-enumerating. ``baud``: the serial speed the host's end
    starts at (a pty carries bytes at any speed; :meth:`host_baud` reads what the host set, for devices
    that model a speed mismatch).
    """

    def __init__(self, link_dir: str | None = None, name: str = "tty", baud: int | None = None) -> None:
        self._baud = baud
        self._own_dir = link_dir is None
        self._dir = link_dir or tempfile.mkdtemp(prefix="glassmap-pty-")
        self.path = os.path.join(self._dir, name)
        self._master = self._slave = -1
        self._writer: asyncio.StreamWriter | None = None
        self._make_pair()

    def _make_pair(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        if self._baud is not None:
            attrs = termios.tcgetattr(self._slave)
            attrs[4] = attrs[5] = _SPEED_CONST[self._baud]
            termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        tmp = self.path + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(self._slave), tmp)
        os.replace(tmp, self.path)

    async def open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """Stream pair on the device (master) side of the current pty."""
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=1 << 20)
        await loop.connect_read_pipe(
            lambda: asyncio.StreamReaderProtocol(reader), os.fdopen(os.dup(self._master), "rb", 0)
        )
        w_transport, w_protocol = await loop.connect_write_pipe(
            lambda: asyncio.streams.FlowControlMixin(loop), os.fdopen(os.dup(self._master), "wb", 0)
        )
        self._writer = asyncio.StreamWriter(w_transport, w_protocol, reader, loop)
        return reader, self._writer

    def host_baud(self) -> int | None:
        """The output speed (baud) the host set on its end of the pty; None when closed or not a standard speed."""
        if self._master < 0:
            return None
        try:
            return _SPEED_BAUD.get(termios.tcgetattr(self._master)[5])
        except (termios.error, OSError):
            return None

    def hangup(self) -> None:
        """Close the pty pair: the host's reads fail and its writes go nowhere."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def reopen(self) -> None:
        """A new pty pair behind the same ``path``."""
        self.hangup()
        self._make_pair()

    def close(self) -> None:
        self.hangup()
        if os.path.lexists(self.path):
            os.unlink(self.path)
        if self._own_dir:
            try:
                os.rmdir(self._dir)
            except OSError:
                pass


async def serve_tcp(handler: Handler, host: str = "127.0.0.1", port: int = 0) -> asyncio.base_events.Server:
    """Start a TCP server calling ``handler(reader, writer)`` per connection; port 0 picks a free port.

    The bound port is ``server.sockets[0].getsockname()[1]``.
    """
    return await asyncio.start_server(handler, host, port)


async def serve_pty(handler: Handler, endpoint: PtyEndpoint) -> asyncio.Task:
    """Run ``handler`` on the device side of ``endpoint`` as a task (the host opens ``endpoint.path``)."""
    reader, writer = await endpoint.open()
    return asyncio.create_task(handler(reader, writer))
