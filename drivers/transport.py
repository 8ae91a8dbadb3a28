"""Byte-stream transports opened from a URL, with taps that see every byte in and out.

URLs:
- ``tcp://HOST:PORT``                          TCP client (e.g. tcp://192.168.0.10:10940)
- ``serial:///dev/ttyACM0?baud=115200``        serial port or pseudo-terminal (pyserial)

A tap is a callable ``tap(direction, host_time, data)`` with direction ``"rx"`` (device -> host) or
``"tx"`` (host -> device) and host_time from ``time.monotonic()``; taps are used for recording.
"""

from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import parse_qs, urlparse

from drivers.errors import InvalidURL, TransportClosed, TransportError

Tap = Callable[[str, float, bytes], None]


@dataclass(frozen=True)
class TransportURL:
    scheme: str
    host: str = ""
    port: int = 0
    path: str = ""
    baud: int = 115200

    @classmethod
    def parse(cls, url: str) -> TransportURL:
        """Parse and check a URL without opening anything; InvalidURL (a ValueError) says what is wrong."""
        try:
            u = urlparse(url)
            port = u.port
        except ValueError as exc:  # urlparse's port check: "Port could not be cast to integer value", ...
            raise InvalidURL(f"bad URL {url!r}: {exc}; expected tcp://HOST:PORT or serial:///dev/PATH") from None
        if u.scheme == "tcp":
            if not u.hostname or port is None:
                raise InvalidURL(f"bad TCP URL {url!r}: expected tcp://HOST:PORT (PORT a number, 1-65535)")
            if port == 0:
                raise InvalidURL(f"bad TCP URL {url!r}: port 0 cannot be connected to")
            return cls("tcp", host=u.hostname, port=port)
        if u.scheme == "serial":
            if not u.path or u.netloc:
                raise InvalidURL(f"bad serial URL {url!r}: expected serial:///dev/ttyXXX[?baud=N] (three slashes)")
            q = parse_qs(u.query)
            unknown = sorted(set(q) - {"baud"})
            if unknown:
                raise InvalidURL(f"bad serial URL {url!r}: unknown option {unknown[0]!r} (only baud=N)")
            try:
                baud = int(q.get("baud", ["115200"])[0])
            except ValueError:
                raise InvalidURL(f"bad serial URL {url!r}: baud must be a whole number, e.g. ?baud=9600") from None
            if baud <= 0:
                raise InvalidURL(f"bad serial URL {url!r}: baud must be > 0")
            return cls("serial", path=u.path, baud=baud)
        raise InvalidURL(f"unsupported device URL {url!r}: use tcp://HOST:PORT or serial:///dev/PATH[?baud=N]")


class Transport(ABC):
    """A bidirectional byte stream. Subclasses implement ``_read``, ``_write`` and ``_close``."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.taps: list[Tap] = []
        self.bytes_in = 0
        self.bytes_out = 0
        self.last_read_time = 0.0  # host time (time.monotonic) of the last read, as the taps saw it
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    async def read(self, max_bytes: int = 65536) -> bytes:
        """Return the next available bytes (at least one). Raises TransportClosed at EOF."""
        if self._closed:
            raise TransportClosed(f"{self.url}: transport is closed")
        try:
            data = await self._read(max_bytes)
        except (OSError, asyncio.IncompleteReadError) as exc:
            raise TransportClosed(f"{self.url}: link lost ({exc})") from exc
        if not data:
            raise TransportClosed(f"{self.url}: peer closed the connection")
        self.bytes_in += len(data)
        self.last_read_time = time.monotonic()
        self._tap("rx", data, self.last_read_time)
        return data

    async def write(self, data: bytes, *, at: float | None = None) -> None:
        """Send bytes and wait until they are handed to the OS. ``at``: the host time the taps see (default
        now), so that a caller who noted the time of a command records the same time."""
        if self._closed:
            raise TransportClosed(f"{self.url}: transport is closed")
        self._tap("tx", data, time.monotonic() if at is None else at)
        try:
            await self._write(data)
        except OSError as exc:
            raise TransportClosed(f"{self.url}: write failed ({exc})") from exc
        self.bytes_out += len(data)

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            await self._close()
        except OSError:
            pass

    async def set_baudrate(self, baud: int) -> None:
        """Change the line speed (serial only)."""
        raise TransportError(f"{self.url}: this transport has no baud rate")

    def _tap(self, direction: str, data: bytes, t: float) -> None:
        for tap in self.taps:
            tap(direction, t, data)

    async def __aenter__(self) -> Transport:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    @abstractmethod
    async def _read(self, max_bytes: int) -> bytes: ...

    @abstractmethod
    async def _write(self, data: bytes) -> None: ...

    @abstractmethod
    async def _close(self) -> None: ...


class StreamTransport(Transport):
    """Transport over an asyncio StreamReader/StreamWriter pair (TCP and serial)."""

    def __init__(self, url: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        super().__init__(url)
        self._reader = reader
        self._writer = writer

    async def _read(self, max_bytes: int) -> bytes:
        return await self._reader.read(max_bytes)

    async def _write(self, data: bytes) -> None:
        self._writer.write(data)
        await self._writer.drain()

    async def _close(self) -> None:
        self._writer.close()
        try:
            await asyncio.wait_for(self._writer.wait_closed(), 1.0)
        except (asyncio.TimeoutError, OSError):
            pass

    async def set_baudrate(self, baud: int) -> None:
        serial = getattr(self._writer.transport, "serial", None)
        if serial is None:
            await super().set_baudrate(baud)
            return
        await self._writer.drain()
        serial.baudrate = baud


async def open_transport(url: str, *, timeout: float = 5.0) -> Transport:
    """Open a transport from a URL (see module docstring). Raises TransportError with the reason."""
    u = TransportURL.parse(url)
    try:
        if u.scheme == "tcp":
            reader, writer = await asyncio.wait_for(asyncio.open_connection(u.host, u.port), timeout)
        else:
            import serial_asyncio_fast

            reader, writer = await asyncio.wait_for(
                serial_asyncio_fast.open_serial_connection(url=u.path, baudrate=u.baud), timeout
            )
    except asyncio.TimeoutError:
        raise TransportError(f"{url}: no connection within {timeout:.1f} s (device powered? address right?)") from None
    except OSError as exc:
        raise TransportError(f"{url}: cannot open ({exc.strerror or exc})") from exc
    except Exception as exc:  # pyserial raises SerialException (an OSError subclass on most versions)
        raise TransportError(f"{url}: cannot open ({exc})") from exc
    return StreamTransport(url, reader, writer)
