"""Async client of a Hokuyo SCIP 2.0 laser (UTM-30LX-EW over TCP; USB models over serial).

    async with HokuyoClient.connect("tcp://192.168.0.10:10940", HokuyoSettings(cluster=1)) as laser:
        async for scan in laser.scans():      # glassmap.types.Scan, metres, laser frame
            ...

Opening: QT (confirmed) to stop whatever runs, PP (geometry and range limits come from it), VV, II, a
TM0/TM1.../TM2 time sync, then an ME (MD, NE, ND) stream with the chosen steps, cluster and skip. A reader
task feeds every byte to the link's :class:`~drivers.hokuyo.session.HokuyoSession` (the receive side, shared
with the raw replay; corrupt input is counted, never fatal), a supervisor
reconnects with exponential back-off when the link drops or the watchdog sees no scan, and restores the
same stream. ``close()`` stops the stream with a confirmed QT (also from ``async with`` on errors and
Ctrl-C). Scans wait in a bounded queue: when the consumer falls behind the oldest are dropped and counted.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass

from drivers.capture import CaptureRecorder
from drivers.clock_jit import warm_up as warm_up_clock
from drivers.connecting import Connecting
from drivers.errors import DeviceTimeout, DriverError, TransportClosed
from drivers.hokuyo.errors import BadValue, ScipStatusError, SensorSilent, StopNotConfirmed
from drivers.hokuyo.scip import Reply, encode_command, scan_params
from drivers.hokuyo.scip import warm_up as warm_up_decoders
from drivers.hokuyo.session import HokuyoSession, HokuyoStats, SensorParams, scan_from_reply
from drivers.transport import Tap, Transport, open_transport
from glassmap.types import LaserGeometry, Scan

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HokuyoSettings:
    """Client settings. Times in seconds.

    multi_echo: NE/ND instead of ME/MD; intensities: ME/NE (else MD/ND); start_step/end_step: default the
    PP AMIN/AMAX; cluster: steps per beam (min of their valid readings); skip: scans skipped between two
    sent (0-9); timeout: per request; connect_timeout: to open the link; watchdog: time without a scan
    before the link is considered dead (None: max(0.5, 20 scan times)); reconnect: reconnect after a lost
    link (else the error ends ``scans()``); backoff: (first, max) delay between attempts; queue_size: scans
    buffered for the consumer; time_sync / tm_samples: TM1 round trips at each connect; stream: False opens
    the link and reads PP/VV/II only (for probing; use :meth:`HokuyoClient.request` for more).
    """

    multi_echo: bool = False
    intensities: bool = True
    start_step: int | None = None
    end_step: int | None = None
    cluster: int = 1
    skip: int = 0
    timeout: float = 1.0
    connect_timeout: float = 3.0
    watchdog: float | None = None
    reconnect: bool = True
    backoff: tuple[float, float] = (0.05, 5.0)
    queue_size: int = 64
    time_sync: bool = True
    tm_samples: int = 8
    stream: bool = True

    def __post_init__(self) -> None:
        if not (0 <= self.cluster <= 99 and 0 <= self.skip <= 9 and self.queue_size >= 1 and self.tm_samples >= 1
                and self.timeout > 0):
            raise ValueError("HokuyoSettings: cluster 0-99, skip 0-9, queue_size >= 1, tm_samples >= 1, timeout > 0")
        if self.start_step is not None and self.end_step is not None and self.end_step < self.start_step:
            raise ValueError(f"end_step {self.end_step} < start_step {self.start_step}")

    @property
    def command(self) -> str:
        """The stream command these settings ask for (ME, MD, NE or ND)."""
        return ("NE" if self.intensities else "ND") if self.multi_echo else ("ME" if self.intensities else "MD")


class _Link:
    """One connection: transport, reader task, pending requests (the receive state is in the session)."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self.pending: deque[tuple[bytes, asyncio.Future]] = deque()
        self.rx_task: asyncio.Task | None = None
        self.lost = asyncio.Event()
        self.error: BaseException | None = None
        self.last_scan = time.monotonic()  # of any stream, or when the link or stream started


_END = object()
_decoders_warm = False


async def _warm_decoders() -> None:
    """Load the compiled SCIP decoders and clock fit once per process (compile them, the first time on a
    machine), in a thread: the event loop keeps serving meanwhile, and the first scan does not wait for them."""
    global _decoders_warm
    if not _decoders_warm:
        await asyncio.to_thread(warm_up_decoders)
        await asyncio.to_thread(warm_up_clock)
        _decoders_warm = True


class HokuyoClient:
    """Async SCIP client. Create it with :meth:`connect`; settings in :class:`HokuyoSettings`.

    url: ``tcp://HOST:PORT`` or ``serial:///dev/ttyACM0``; taps: transport taps (kept across
    reconnections; ``client.taps`` may be changed later).
    """

    def __init__(self, url: str, settings: HokuyoSettings | None = None, taps: Iterable[Tap] = ()) -> None:
        self.url = url
        self.settings = s = settings or HokuyoSettings()
        self.taps: list[Tap] = list(taps)
        self.stats = HokuyoStats()
        self.session = HokuyoSession(self.stats, name=url)
        self.version: dict[str, str] = {}
        self.status: dict[str, str] = {}
        self.geometry: LaserGeometry | None = None
        self.last_error: BaseException | None = None
        self._queue: asyncio.Queue = asyncio.Queue(maxsize=s.queue_size + 1)
        self._queue_size = s.queue_size
        self._link: _Link | None = None
        self._supervisor: asyncio.Task | None = None
        self._closing = self._closed = False

    # -- public API -----------------------------------------------------------------------------------
    @classmethod
    def connect(cls, url: str, settings: HokuyoSettings | None = None, *,
                taps: Iterable[Tap] = ()) -> Connecting[HokuyoClient]:
        """Open the link, read PP/VV/II, sync the clock and start streaming (unless ``settings.stream`` is
        False). Await the result, or ``async with`` it to have the client closed on exit. Raises
        TransportError (cannot open), DriverError (the sensor does not answer right), ValueError (bad steps).
        """

        async def factory() -> HokuyoClient:
            self = cls(url, settings, taps)
            try:
                await self._connect_once()
            except BaseException:
                await self._drop_link()
                raise
            self._supervisor = asyncio.create_task(self._supervise())
            return self

        return Connecting(factory)

    @property
    def command(self) -> str:
        """The stream command in use (ME, MD, NE or ND)."""
        return self.settings.command

    @property
    def params(self) -> SensorParams | None:
        """The sensor's PP parameters (None before the first connect)."""
        return self.session.params

    @property
    def pp(self) -> dict[str, str]:
        """The raw PP fields."""
        return self.session.pp

    @property
    def watchdog(self) -> float:
        st = self.params.scan_time if self.params else 0.025
        w = self.settings.watchdog
        return w if w is not None else max(0.5, 20 * st * (self.settings.skip + 1))

    async def scans(self) -> AsyncIterator[Scan]:
        """Scans in arrival order until :meth:`close`; raises the link error if reconnecting is off."""
        while True:
            item = await self._queue.get()
            if item is _END:
                self._put(_END)  # let other consumers end too
                if isinstance(self.last_error, BaseException) and not self._closing:
                    raise self.last_error
                return
            yield item

    async def request(self, command: str, params: str = "", string: str = "", *, ok: Iterable[str] = ("00",),
                      timeout: float | None = None) -> Reply:
        """Send one command on the current link and return its reply (ScipStatusError if not ``ok``)."""
        if self._link is None or self._link.lost.is_set():
            raise TransportClosed(f"{self.url}: not connected")
        return await self._request(self._link, command, params, string, ok=tuple(ok), timeout=timeout)

    async def close(self) -> None:
        """Stop the stream (QT, confirmed), close the link, end ``scans()``. Raises StopNotConfirmed if the
        sensor never confirmed the stop (the link is closed anyway)."""
        if self._closed:
            return
        self._closing = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._supervisor
        failure: BaseException | None = None
        link = self._link
        if link is not None and not link.lost.is_set():
            try:
                await self._stop_stream(link)
            except (DriverError, OSError) as exc:
                failure = exc
        await self._drop_link()
        self._closed = True
        self._put(_END)
        if failure is not None:
            if isinstance(failure, StopNotConfirmed):
                raise failure
            log.warning("%s: could not stop the stream cleanly: %s", self.url, failure)

    async def __aenter__(self) -> HokuyoClient:
        return self

    async def __aexit__(self, exc_type, exc, tb) -> None:
        try:
            await self.close()
        except DriverError as err:
            if exc is None:
                raise
            log.warning("%s: while closing after %r: %s", self.url, exc, err)

    # -- connection -----------------------------------------------------------------------------------
    async def _connect_once(self) -> None:
        s = self.settings
        transport = await open_transport(self.url, timeout=s.connect_timeout)
        transport.taps = self.taps  # shared list: taps survive reconnection and may be added later
        link = _Link(transport)
        self.session.new_link()
        link.rx_task = asyncio.create_task(self._rx_loop(link))
        self._link = link
        await self._stop_stream(link)
        await self._request(link, "PP")
        if self.session.params is None:
            raise self.session.params_error or BadValue("PP reply not understood", command="PP")
        p = self.session.params
        self.version = dict((await self._request(link, "VV")).fields)
        self.status = dict((await self._request(link, "II")).fields)
        start = p.amin if s.start_step is None else s.start_step
        end = p.amax if s.end_step is None else s.end_step
        if not p.amin <= start <= end <= p.amax:
            raise ValueError(f"steps {start}..{end} outside the sensor's {p.amin}..{p.amax}")
        self.geometry = p.geometry(start, end, s.cluster)
        if not s.stream:
            return
        await _warm_decoders()  # before the scan watchdog runs
        await self._time_sync(link)
        params = scan_params(start, end, max(s.cluster, 1), s.skip, 0)
        try:  # sending it tells the session to take scans (they may follow the acknowledgement in the same read)
            await self._request(link, self.command, params)
        except BaseException:
            self.session.stop_stream()
            raise
        link.last_scan = time.monotonic()

    async def _time_sync(self, link: _Link) -> None:
        """TM0, TM1 x tm_samples, TM2: the session turns the round trips into the clock's offset."""
        if not self.settings.time_sync:
            return
        try:
            await self._request(link, "TM", "0", ok=("00", "02"))
        except ScipStatusError as exc:
            self.stats.time_sync_failures += 1
            log.warning("%s: time sync refused (%s); stamping from arrival times", self.url, exc)
            return
        try:
            for _ in range(self.settings.tm_samples):
                await self._request(link, "TM", "1")
        finally:
            with contextlib.suppress(ScipStatusError):
                await self._request(link, "TM", "2", ok=("00", "03"))

    async def _stop_stream(self, link: _Link, attempts: int = 3) -> None:
        """QT until the sensor answers and no scan follows the answer."""
        window = max(0.08, 3 * (self.params.scan_time if self.params else 0.025))
        for _ in range(attempts):
            try:
                await self._request(link, "QT")
            except DeviceTimeout:
                continue
            t_reply = time.monotonic()
            await asyncio.sleep(window)
            if link.last_scan <= t_reply:
                return
        raise StopNotConfirmed(f"{self.url}: sensor kept streaming or never answered after {attempts} QT")

    async def _request(self, link: _Link, command: str, params: str = "", string: str = "", *,
                       ok: tuple[str, ...] = ("00",), timeout: float | None = None) -> Reply:
        """Send a command (telling the session) and wait for its reply."""
        line = encode_command(command, params, string)
        fut = asyncio.get_running_loop().create_future()
        entry = (line[:-1], fut)
        link.pending.append(entry)
        timeout = timeout or self.settings.timeout
        try:
            t = time.monotonic()
            self.session.sent(t, line)  # before the write: a reply may come before write() returns
            await link.transport.write(line, at=t)  # taps (recordings) see the same time as the session
            reply = await asyncio.wait_for(fut, timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"{self.url}: no reply to {line[:-1].decode()!r} within "
                                f"{timeout:.2f} s (sensor busy, hung or rebooting?)") from None
        finally:
            with contextlib.suppress(ValueError):
                link.pending.remove(entry)
        return reply.raise_for_status(ok)

    async def _drop_link(self) -> None:
        link, self._link = self._link, None
        self.session.stop_stream()
        if link is None:
            return
        await link.transport.close()
        if link.rx_task is not None:
            link.rx_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await link.rx_task

    async def _supervise(self) -> None:
        try:
            await self._watch()
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # never leave scans() waiting forever on a dead supervisor
            log.exception("%s: supervisor failed", self.url)
            self.last_error = exc
            self._put(_END)

    async def _watch(self) -> None:
        while not self._closing:
            link = self._link
            reason = ""
            if link is None:
                reason = "no link"
            else:
                try:
                    await asyncio.wait_for(link.lost.wait(), min(self.watchdog / 4, 0.25))
                    reason = f"link lost ({link.error})"
                except asyncio.TimeoutError:
                    if self.session.streaming and time.monotonic() - link.last_scan > self.watchdog:
                        self.stats.watchdog_trips += 1
                        reason = f"no scan for {self.watchdog:.2f} s (watchdog)"
            if not reason:
                continue
            if not self.settings.reconnect:
                self.last_error = link.error if link and link.error else SensorSilent(f"{self.url}: {reason}")
                await self._drop_link()
                self._put(_END)
                return
            await self._reconnect(reason)

    async def _reconnect(self, reason: str) -> None:
        log.warning("%s: %s; reconnecting", self.url, reason)
        await self._drop_link()
        delay = self.settings.backoff[0]
        while not self._closing:
            try:
                await self._connect_once()
                self.stats.reconnects += 1
                log.info("%s: reconnected", self.url)
                return
            except (DriverError, OSError, ValueError) as exc:
                self.last_error = exc
                log.info("%s: reconnect failed (%s); next try in %.2f s", self.url, exc, delay)
                await self._drop_link()
                await asyncio.sleep(delay)
                delay = min(2 * delay, self.settings.backoff[1])

    # -- receiving ------------------------------------------------------------------------------------
    async def _rx_loop(self, link: _Link) -> None:
        try:
            while True:
                data = await link.transport.read()
                scans, replies = self.session.received(link.transport.last_read_time, data)  # the taps' time
                if self.session.last_scan is not None and self.session.last_scan > link.last_scan:
                    link.last_scan = self.session.last_scan
                for scan in scans:
                    if self._put(scan):
                        self.stats.dropped += 1
                for reply in replies:
                    self._match(link, reply)
        except (TransportClosed, OSError) as exc:
            link.error = exc
        except Exception as exc:  # a bug must not leave the link half dead: report it and reconnect
            log.exception("%s: receive loop failed", self.url)
            link.error = exc
        finally:
            link.lost.set()
            for _, fut in link.pending:
                if not fut.done():
                    fut.set_exception(TransportClosed(f"{self.url}: link lost while waiting for a reply"))

    def _match(self, link: _Link, reply: Reply) -> None:
        for entry in link.pending:
            if entry[0] == reply.echo.raw and not entry[1].done():
                entry[1].set_result(reply)
                link.pending.remove(entry)
                return
        self.session.unmatched(reply)

    def _put(self, item) -> bool:
        """Queue without blocking; drop the oldest scan when full. True if one was dropped."""
        dropped = False
        while self._queue.qsize() >= self._queue_size:
            old = self._queue.get_nowait()
            if old is _END:
                self._queue.put_nowait(old)
                return False
            dropped = True
        self._queue.put_nowait(item)
        return dropped


async def record(url: str, path: str, settings: HokuyoSettings | None = None, *, scans: int = 100,
                 note: str = "") -> HokuyoStats:
    """Connect, take ``scans`` scans, close, and save every byte both ways to a capture file (.jsonl)."""
    rec = CaptureRecorder("hokuyo", note=note)
    client = await HokuyoClient.connect(url, settings, taps=[rec])
    try:
        n = 0
        async for _ in client.scans():
            n += 1
            if n >= scans:
                break
    finally:
        try:
            await client.close()
        finally:
            rec.capture.save(path)
    return client.stats


__all__ = ["HokuyoClient", "HokuyoSettings", "HokuyoStats", "SensorParams", "record", "scan_from_reply"]
