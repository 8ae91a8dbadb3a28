"""Async client of a Hokuyo SCIP 2.0 laser (UTM-30LX-EW over TCP; USB models over serial).

    async with await HokuyoClient.connect("tcp://192.168.0.10:10940") as laser:
        async for scan in laser.scans():      # glassmap.types.Scan, metres, laser frame
            ...

Opening: QT (confirmed) to stop whatever runs, PP (geometry and range limits come from it), VV, II, a
TM0/TM1.../TM2 time sync, then an ME (MD, NE, ND) stream with the chosen steps, cluster and skip. A reader
task parses every byte (the codec reports corrupt input; it is counted, never fatal), a supervisor
reconnects with exponential back-off when the link drops or the watchdog sees no scan, and restores the
same stream. ``close()`` stops the stream with a confirmed QT (also from ``async with`` on errors and
Ctrl-C). Scans wait in a bounded queue: when the consumer falls behind the oldest are dropped and counted.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass

import numpy as np

from drivers.capture import CaptureRecorder
from drivers.errors import DeviceTimeout, DriverError, TransportClosed
from drivers.hokuyo.clock import ClockMapper, RoundTrip, TimestampUnwrapper
from drivers.hokuyo.errors import (
    BadValue,
    GarbageData,
    ScipProtocolError,
    ScipStatusError,
    SensorSilent,
    StopNotConfirmed,
)
from drivers.hokuyo.scip import (
    SCAN_COMMANDS,
    Reply,
    ScanReply,
    ScipParser,
    distances_to_metres,
    encode_command,
    expected_steps,
    scan_params,
)
from drivers.transport import Tap, Transport, open_transport
from glassmap.types import LaserGeometry, Scan

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorParams:
    """The PP reply: model, range limits (mm), angular resolution and step range, scan speed (rpm)."""

    model: str
    dmin: int
    dmax: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int

    @classmethod
    def from_pp(cls, fields: dict[str, str]) -> SensorParams:
        """Parse PP fields; BadValue naming the field if one is missing or not a number."""
        try:
            return cls(fields.get("MODL", "?"), int(fields["DMIN"]), int(fields["DMAX"]), int(fields["ARES"]),
                       int(fields["AMIN"]), int(fields["AMAX"]), int(fields["AFRT"]), int(fields["SCAN"]))
        except (KeyError, ValueError) as exc:
            raise BadValue(f"PP reply lacks a usable {exc} field: {fields}", command="PP") from None

    @property
    def scan_time(self) -> float:
        """Seconds per revolution."""
        return 60.0 / self.scan_rpm

    def step_angle(self, step: float) -> float:
        """Angle (rad, laser frame, CCW positive, front = 0) of a step."""
        return (step - self.afrt) * 2 * math.pi / self.ares

    def geometry(self, start: int, end: int, cluster: int = 1) -> LaserGeometry:
        """Beam layout of a scan over steps start..end; a cluster's beam points at its centre step."""
        c = max(cluster, 1)
        return LaserGeometry(n_beams=expected_steps(start, end, c), angle_min=self.step_angle(start + (c - 1) / 2),
                             angle_increment=c * 2 * math.pi / self.ares, range_min=self.dmin / 1000.0,
                             range_max=self.dmax / 1000.0, scan_time=self.scan_time)


@dataclass
class HokuyoStats:
    """Counters since the client was created.

    received: good scans decoded; corrupted: messages discarded by the codec (checksum, truncation, bad
    echo or values); error_statuses: stream messages with a non-99 status (0L, 0M, ...); dropped: scans
    thrown away because the consumer fell behind (bounded queue); missed: scans the sensor's stamps say were
    made but did not arrive intact; stale: scans of a stream we did not (or no longer) ask for;
    garbage_bytes: line noise between messages; unexpected: replies nobody asked for;
    reconnects / watchdog_trips; clock_jumps / clock_outliers: sensor clock events; time_sync_failures.
    """

    received: int = 0
    corrupted: int = 0
    error_statuses: int = 0
    dropped: int = 0
    missed: int = 0
    stale: int = 0
    garbage_bytes: int = 0
    unexpected: int = 0
    reconnects: int = 0
    watchdog_trips: int = 0
    clock_jumps: int = 0
    clock_outliers: int = 0
    time_sync_failures: int = 0


class _Link:
    """One connection: transport, parser, reader task, pending requests, per-connection clock."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self.parser = ScipParser()
        self.pending: deque[tuple[bytes, asyncio.Future]] = deque()
        self.rx_task: asyncio.Task | None = None
        self.lost = asyncio.Event()
        self.error: BaseException | None = None
        self.last_scan = time.monotonic()
        self.unwrap = TimestampUnwrapper()
        self.clock = ClockMapper()
        self.last_stamp_ms: int | None = None
        self.jumps = self.outliers = 0


_END = object()


class HokuyoClient:
    """Async SCIP client. Use :meth:`connect` (or ``async with await HokuyoClient.connect(...)``).

    url: ``tcp://HOST:PORT`` or ``serial:///dev/ttyACM0``. start_step/end_step: default the PP AMIN/AMAX;
    cluster: steps per beam (min of their valid readings); skip: scans skipped between two sent (0-9);
    multi_echo: NE/ND instead of ME/MD; intensities: ME/NE (else MD/ND); taps: transport taps (kept across
    reconnections; ``client.taps`` may be changed later); timeout: per request (s); watchdog: seconds
    without a scan before the link is considered dead (default max(0.5, 20 scan times));
    reconnect: reconnect after a lost link (else the error ends ``scans()``); backoff: (first, max) delay (s);
    queue_size: scans buffered for the consumer; time_sync / tm_samples: TM1 round trips at each connect;
    stream: False opens the link and reads PP/VV/II only (for probing; use :meth:`request` for more).
    """

    def __init__(self, url: str, *, multi_echo: bool = False, intensities: bool = True,
                 start_step: int | None = None, end_step: int | None = None, cluster: int = 1, skip: int = 0,
                 taps: Iterable[Tap] = (), timeout: float = 1.0, connect_timeout: float = 3.0,
                 watchdog: float | None = None, reconnect: bool = True, backoff: tuple[float, float] = (0.05, 5.0),
                 queue_size: int = 64, time_sync: bool = True, tm_samples: int = 8, stream: bool = True) -> None:
        if not (0 <= cluster <= 99 and 0 <= skip <= 9 and queue_size >= 1 and tm_samples >= 1 and timeout > 0):
            raise ValueError("HokuyoClient: cluster 0-99, skip 0-9, queue_size >= 1, tm_samples >= 1, timeout > 0")
        if start_step is not None and end_step is not None and end_step < start_step:
            raise ValueError(f"end_step {end_step} < start_step {start_step}")
        self.url = url
        self.multi_echo, self.intensities = multi_echo, intensities
        self.start_step, self.end_step, self.cluster, self.skip = start_step, end_step, max(cluster, 1), skip
        self.taps: list[Tap] = list(taps)
        self.timeout, self.connect_timeout = timeout, connect_timeout
        self._watchdog = watchdog
        self.reconnect, self.backoff = reconnect, backoff
        self.time_sync, self.tm_samples = time_sync, tm_samples
        self.stream = stream
        self.stats = HokuyoStats()
        self.params: SensorParams | None = None
        self.pp: dict[str, str] = {}
        self.version: dict[str, str] = {}
        self.status: dict[str, str] = {}
        self.geometry: LaserGeometry | None = None
        self.last_error: BaseException | None = None
        self._queue: asyncio.Queue = asyncio.Queue(maxsize=queue_size + 1)
        self._queue_size = queue_size
        self._link: _Link | None = None
        self._supervisor: asyncio.Task | None = None
        self._streaming = False
        self._stream_prefix = b""
        self._seq = 0
        self._closing = self._closed = False

    # -- public API -----------------------------------------------------------------------------------
    @classmethod
    async def connect(cls, url: str, **kwargs) -> HokuyoClient:
        """Create a client, open the link, read PP/VV/II, sync the clock and start streaming."""
        self = cls(url, **kwargs)
        try:
            await self._connect_once()
        except BaseException:
            await self._drop_link()
            raise
        self._supervisor = asyncio.create_task(self._supervise())
        return self

    @property
    def command(self) -> str:
        """The stream command in use (ME, MD, NE or ND)."""
        return ("NE" if self.intensities else "ND") if self.multi_echo else ("ME" if self.intensities else "MD")

    @property
    def watchdog(self) -> float:
        st = self.params.scan_time if self.params else 0.025
        return self._watchdog if self._watchdog is not None else max(0.5, 20 * st * (self.skip + 1))

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
        transport = await open_transport(self.url, timeout=self.connect_timeout)
        transport.taps = self.taps  # shared list: taps survive reconnection and may be added later
        link = _Link(transport)
        link.rx_task = asyncio.create_task(self._rx_loop(link))
        self._link = link
        await self._stop_stream(link)
        self.pp = dict((await self._request(link, "PP")).fields)
        self.params = p = SensorParams.from_pp(self.pp)
        self.version = dict((await self._request(link, "VV")).fields)
        self.status = dict((await self._request(link, "II")).fields)
        start = p.amin if self.start_step is None else self.start_step
        end = p.amax if self.end_step is None else self.end_step
        if not p.amin <= start <= end <= p.amax:
            raise ValueError(f"steps {start}..{end} outside the sensor's {p.amin}..{p.amax}")
        self.geometry = p.geometry(start, end, self.cluster)
        link.clock = ClockMapper(default_latency=p.scan_time)
        if not self.stream:
            return
        await self._time_sync(link)
        params = scan_params(start, end, self.cluster, self.skip, 0)
        self._stream_prefix = (self.command + params[:-2]).encode("ascii")
        self._streaming = True  # scans may follow the acknowledgement in the same read
        try:
            await self._request(link, self.command, params)
        except BaseException:
            self._streaming = False
            raise
        link.last_scan = time.monotonic()

    async def _time_sync(self, link: _Link) -> None:
        if not self.time_sync:
            return
        try:
            await self._request(link, "TM", "0", ok=("00", "02"))
        except ScipStatusError as exc:
            self.stats.time_sync_failures += 1
            log.warning("%s: time sync refused (%s); stamping from arrival times", self.url, exc)
            return
        samples = []
        try:
            for _ in range(self.tm_samples):
                # t1 is when the reply's bytes arrived, not when this coroutine resumed (on a busy machine
                # that can be milliseconds later; a replay of the recorded bytes sees the arrival time)
                t0 = time.monotonic()
                reply, t1 = await self._request_at(link, "TM", "1")
                samples.append(RoundTrip(t0, t1, link.unwrap.unwrap(reply.time_ms) / 1000.0))
        finally:
            with contextlib.suppress(ScipStatusError):
                await self._request(link, "TM", "2", ok=("00", "03"))
        link.clock.add_round_trips(samples)

    async def _stop_stream(self, link: _Link, attempts: int = 3) -> None:
        """QT until the sensor answers and no scan follows the answer."""
        window = max(0.08, 3 * (self.params.scan_time if self.params else 0.025))
        for _ in range(attempts):
            self._streaming = False
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
        return (await self._request_at(link, command, params, string, ok=ok, timeout=timeout))[0]

    async def _request_at(self, link: _Link, command: str, params: str = "", string: str = "", *,
                          ok: tuple[str, ...] = ("00",), timeout: float | None = None) -> tuple[Reply, float]:
        """Send a command and wait for its reply; returns (reply, host time the reply's bytes arrived)."""
        line = encode_command(command, params, string)
        fut = asyncio.get_running_loop().create_future()
        entry = (line[:-1], fut)
        link.pending.append(entry)
        try:
            await link.transport.write(line)
            reply, arrived = await asyncio.wait_for(fut, timeout or self.timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"{self.url}: no reply to {line[:-1].decode()!r} within "
                                f"{timeout or self.timeout:.2f} s (sensor busy, hung or rebooting?)") from None
        finally:
            with contextlib.suppress(ValueError):
                link.pending.remove(entry)
        return reply.raise_for_status(ok), arrived

    async def _drop_link(self) -> None:
        link, self._link = self._link, None
        self._streaming = False
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
                    if self._streaming and time.monotonic() - link.last_scan > self.watchdog:
                        self.stats.watchdog_trips += 1
                        reason = f"no scan for {self.watchdog:.2f} s (watchdog)"
            if not reason:
                continue
            if not self.reconnect:
                self.last_error = link.error if link and link.error else SensorSilent(f"{self.url}: {reason}")
                await self._drop_link()
                self._put(_END)
                return
            await self._reconnect(reason)

    async def _reconnect(self, reason: str) -> None:
        log.warning("%s: %s; reconnecting", self.url, reason)
        await self._drop_link()
        delay = self.backoff[0]
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
                delay = min(2 * delay, self.backoff[1])

    # -- receiving ------------------------------------------------------------------------------------
    async def _rx_loop(self, link: _Link) -> None:
        try:
            while True:
                data = await link.transport.read()
                now = time.monotonic()
                for item in link.parser.feed(data):
                    self._dispatch(link, item, now)
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

    def _dispatch(self, link: _Link, item: Reply | ScipProtocolError, now: float) -> None:
        if isinstance(item, ScipProtocolError):
            if isinstance(item, GarbageData):
                self.stats.garbage_bytes += item.nbytes
            else:
                self.stats.corrupted += 1
                log.debug("%s: discarded: %s", self.url, item)
            return
        if isinstance(item, ScanReply) and item.status == "99":
            link.last_scan = now
            if self._streaming and item.echo.raw.startswith(self._stream_prefix):
                self._on_scan(link, item, now)
            else:
                self.stats.stale += 1
            return
        for entry in link.pending:
            if entry[0] == item.echo.raw and not entry[1].done():
                entry[1].set_result((item, now))
                link.pending.remove(entry)
                return
        if item.command in SCAN_COMMANDS and item.status != "00":
            self.stats.error_statuses += 1
            log.debug("%s: stream status %s", self.url, item.status)
        else:
            self.stats.unexpected += 1

    def _on_scan(self, link: _Link, item: ScanReply, now: float) -> None:
        p, g = self.params, self.geometry
        ms = link.unwrap.unwrap(item.timestamp_ms)
        if link.last_stamp_ms is not None:
            expected = 1000.0 * p.scan_time * (self.skip + 1)
            gap = ms - link.last_stamp_ms
            if 1.5 * expected < gap < 10_000:
                self.stats.missed += int(round(gap / expected)) - 1
        link.last_stamp_ms = ms
        sensor = ms / 1000.0
        stamp = link.clock.observe(sensor, now)
        self.stats.clock_jumps += link.clock.jumps - link.jumps
        self.stats.clock_outliers += link.clock.outliers - link.outliers
        link.jumps, link.outliers = link.clock.jumps, link.clock.outliers
        self.stats.received += 1
        self._seq += 1
        scan = scan_from_reply(item, p, g, stamp=stamp, sensor_stamp=sensor, seq=self._seq)
        if self._put(scan):
            self.stats.dropped += 1

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


def scan_from_reply(reply: ScanReply, params: SensorParams, geometry: LaserGeometry, *, stamp: float,
                    sensor_stamp: float, seq: int) -> Scan:
    """A decoded scan message as a ``glassmap.types.Scan`` (metres, REP 117 NaN/inf, laser frame).

    For multi-echo replies ``ranges`` is the first echo and ``echoes`` / ``echo_intensities`` hold the
    further ones, shape (n, 2), NaN where a step had fewer echoes."""
    echoes = echo_int = None
    if reply.multi is not None:
        echoes = distances_to_metres(reply.multi[:, 1:], params.dmin, params.dmax)
        if reply.multi_intensities is not None:
            echo_int = np.where(reply.multi[:, 1:] >= 0, reply.multi_intensities[:, 1:], np.nan)
    return Scan(stamp=stamp, ranges=distances_to_metres(reply.distances, params.dmin, params.dmax),
                intensities=None if reply.intensities is None else reply.intensities.astype(np.float64),
                geometry=geometry, sensor_stamp=sensor_stamp, seq=seq, echoes=echoes, echo_intensities=echo_int)


async def record(url: str, path: str, *, scans: int = 100, note: str = "", **kwargs) -> HokuyoStats:
    """Connect, take ``scans`` scans, close, and save every byte both ways to a capture file (.jsonl)."""
    rec = CaptureRecorder("hokuyo", note=note)
    client = await HokuyoClient.connect(url, taps=[rec], **kwargs)
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


__all__ = ["HokuyoClient", "HokuyoStats", "SensorParams", "record", "scan_from_reply"]
