"""The receive side of a Hokuyo SCIP link (sans-IO), shared by the live client and the raw replay.

A :class:`HokuyoSession` is told what the host sent (``sent``) and fed what the sensor returned
(``received``), each with the host time (s) of the write or read. It keeps the per-link state (SCIP
parser, 24-bit stamp unwrapper, sensor-to-host clock, the stream being asked for) and turns the bytes into
``glassmap.types.Scan`` values, counting everything it discards in a :class:`HokuyoStats`. It never reads
a clock and never touches a socket: the client feeds it live bytes, ``runtime.raw_replay`` recorded ones.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from drivers.clock import ClockMapper, RoundTrip
from drivers.hokuyo.clock import TimestampUnwrapper
from drivers.hokuyo.errors import BadValue, GarbageData, ScipProtocolError
from drivers.hokuyo.scip import (
    SCAN_COMMANDS,
    STREAM_COMMANDS,
    InfoReply,
    Reply,
    ScanReply,
    ScipParser,
    TimeReply,
    distances_to_metres,
    expected_steps,
    further_echoes,
)
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
    """Counters since the client (or replay) started.

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


def scan_from_reply(reply: ScanReply, params: SensorParams, geometry: LaserGeometry, *, stamp: float,
                    sensor_stamp: float, seq: int) -> Scan:
    """A decoded scan message as a ``glassmap.types.Scan`` (metres, REP 117 NaN/inf, laser frame).

    For multi-echo replies ``ranges`` is the first echo and ``echoes`` / ``echo_intensities`` hold the
    further ones, shape (n, 2), NaN where a step had fewer echoes."""
    echoes = echo_int = None
    if reply.multi is not None:
        echoes, echo_int = further_echoes(reply.multi, reply.multi_intensities, params.dmin, params.dmax)
    return Scan(stamp=stamp, ranges=distances_to_metres(reply.distances, params.dmin, params.dmax),
                intensities=None if reply.intensities is None else reply.intensities.astype(np.float64),
                geometry=geometry, sensor_stamp=sensor_stamp, seq=seq, echoes=echoes, echo_intensities=echo_int)


class HokuyoSession:
    """Receive state of a SCIP link. ``received`` returns (scans, replies): scans of the stream asked for,
    and every other complete reply (for the caller to match against its requests).

    State that belongs to one connection (parser, unwrapper, clock, stream) is reset by :meth:`new_link`;
    the sensor parameters, the scan sequence number and the counters carry over.
    """

    def __init__(self, stats: HokuyoStats | None = None, name: str = "hokuyo") -> None:
        self.stats = stats if stats is not None else HokuyoStats()
        self.name = name
        self.params: SensorParams | None = None
        self.params_error: BadValue | None = None
        self.pp: dict[str, str] = {}
        self.geometry: LaserGeometry | None = None
        self.seq = 0
        self.links = 0
        self.new_link()

    def new_link(self) -> None:
        """A new connection: fresh parser, unwrapper and clock; no stream asked for."""
        self.parser = ScipParser()
        self.unwrap = TimestampUnwrapper()
        self.clock = ClockMapper(default_latency=self.params.scan_time) if self.params else ClockMapper()
        self.streaming = False
        self.stream_prefix = b""
        self.skip = 0
        self.last_scan: float | None = None  # host time of the last status-99 scan of any stream
        self._last_stamp_ms: int | None = None
        self._jumps = self._outliers = 0
        self._tm_sent: float | None = None
        self._round_trips: list[RoundTrip] = []
        self.links += 1

    # -- host -> sensor ---------------------------------------------------------------------------------
    def sent(self, t: float, data: bytes) -> None:
        """Command bytes the host wrote at host time ``t`` (one or more lines)."""
        for line in data.replace(b"\r", b"\n").split(b"\n"):
            line = line.split(b";")[0]
            cmd = line[:2].decode("ascii", "replace")
            if cmd == "QT":
                self.streaming = False
            elif line == b"TM1":
                self._tm_sent = t
            elif line == b"TM2":
                self.clock.add_round_trips(self._round_trips)
                self._round_trips = []
            elif cmd in STREAM_COMMANDS and len(line) == 15 and line[2:].isdigit():
                self._start_stream(line)

    def _start_stream(self, line: bytes) -> None:
        start, end, cluster, skip = int(line[2:6]), int(line[6:10]), int(line[10:12]), int(line[12:13])
        if self.params is not None:
            self.geometry = self.params.geometry(start, end, max(cluster, 1))
        self.stream_prefix = line[:-2]  # echo of every scan of this stream, without the remaining count
        self.skip = skip
        self.streaming = True

    def stop_stream(self) -> None:
        """The stream request failed: scans that still arrive are stale."""
        self.streaming = False

    # -- sensor -> host ---------------------------------------------------------------------------------
    def received(self, t: float, data: bytes) -> tuple[list[Scan], list[Reply]]:
        """Bytes the host read at host time ``t``: the scans and other replies they complete."""
        scans: list[Scan] = []
        replies: list[Reply] = []
        for item in self.parser.feed(data):
            if isinstance(item, ScipProtocolError):
                if isinstance(item, GarbageData):
                    self.stats.garbage_bytes += item.nbytes
                else:
                    self.stats.corrupted += 1
                    log.debug("%s: discarded: %s", self.name, item)
                continue
            if isinstance(item, ScanReply) and item.status == "99":
                self.last_scan = t
                if self.streaming and self.params is not None and self.geometry is not None \
                        and item.echo.raw.startswith(self.stream_prefix):
                    scans.append(self._scan(item, t))
                else:
                    self.stats.stale += 1
                continue
            if isinstance(item, InfoReply) and item.command == "PP" and item.status == "00":
                self._on_pp(item.fields)
            elif isinstance(item, TimeReply) and item.status == "00" and self._tm_sent is not None:
                sensor = self.unwrap.unwrap(item.time_ms) / 1000.0
                self._round_trips.append(RoundTrip(self._tm_sent, t, sensor))
                self._tm_sent = None
            replies.append(item)
        return scans, replies

    def unmatched(self, reply: Reply) -> None:
        """Count a reply nobody asked for (a stream error status, or an unexpected reply)."""
        if reply.command in SCAN_COMMANDS and reply.status != "00":
            self.stats.error_statuses += 1
            log.debug("%s: stream status %s", self.name, reply.status)
        else:
            self.stats.unexpected += 1

    def _on_pp(self, fields: dict[str, str]) -> None:
        self.pp = dict(fields)
        try:
            self.params = SensorParams.from_pp(fields)
        except BadValue as exc:
            self.params_error = exc
            return
        self.params_error = None
        self.clock = ClockMapper(default_latency=self.params.scan_time)

    def _scan(self, item: ScanReply, t: float) -> Scan:
        p = self.params
        ms = self.unwrap.unwrap(item.timestamp_ms)
        if self._last_stamp_ms is not None:
            expected = 1000.0 * p.scan_time * (self.skip + 1)
            gap = ms - self._last_stamp_ms
            if 1.5 * expected < gap < 10_000:
                self.stats.missed += int(round(gap / expected)) - 1
        self._last_stamp_ms = ms
        sensor = ms / 1000.0
        stamp = self.clock.observe(sensor, t)
        self.stats.clock_jumps += self.clock.jumps - self._jumps
        self.stats.clock_outliers += self.clock.outliers - self._outliers
        self._jumps, self._outliers = self.clock.jumps, self.clock.outliers
        self.stats.received += 1
        self.seq += 1
        return scan_from_reply(item, p, self.geometry, stamp=stamp, sensor_stamp=sensor, seq=self.seq)


__all__ = ["HokuyoSession", "HokuyoStats", "SensorParams", "scan_from_reply"]
