"""Replay of the raw device bytes of a recording through the drivers' own decoding code.

The recorded chunks of each link (/raw/laser, /raw/base: both directions, with the host time each read or
write happened) are fed, in order and with their recorded times, to the same sans-IO pieces the clients
use on a live link: for the Hokuyo the SCIP parser, ``SensorParams`` (from the recorded PP reply), the
24-bit unwrapper and the ``ClockMapper`` (TM1 round trips + the arrival times); for the Pioneer the packet
parser, ``decode_sync2`` / ``model_for`` and the ``OdometryTracker``. A new connection (the client's QT at
connect / the SYNC0 of a new handshake) starts a fresh per-link state exactly as the clients do.

The clients take their arrival times from ``time.monotonic()`` right after the transport read that also
called the recording tap, so replayed stamps agree with the live ones to within microseconds.

Why not the client classes themselves over a fake link? Their handshakes wait on real timeouts and they
read the clock themselves; feeding recorded chunks to their decoding path is exact and as fast as the
decoder.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from drivers.capture import Capture
from glassmap.types import Odometry, Scan
from runtime.readers import ReplayInputError, read_captures

log = logging.getLogger(__name__)


class HokuyoReplayDecoder:
    """The receive path of :class:`drivers.hokuyo.client.HokuyoClient` over recorded chunks."""

    def __init__(self) -> None:
        from drivers.hokuyo.clock import ClockMapper

        self._ClockMapper = ClockMapper
        self.params = None
        self.geometry = None
        self.seq = 0
        self.links = 0
        self.corrupted = 0
        self._new_link()

    def _new_link(self) -> None:
        from drivers.hokuyo.clock import TimestampUnwrapper
        from drivers.hokuyo.scip import ScipParser

        self.parser = ScipParser()
        self.unwrap = TimestampUnwrapper()
        self.clock = self._ClockMapper()
        self.prefix = b""
        self.streaming = False
        self._tm_t0: float | None = None
        self._samples: list = []
        self.links += 1

    def tx(self, t: float, data: bytes) -> None:
        """Host -> sensor bytes written at host time ``t``."""
        from drivers.hokuyo.clock import ClockMapper

        for line in data.replace(b"\r", b"\n").split(b"\n"):
            line = line.split(b";")[0]
            if not line:
                continue
            cmd = line[:2]
            if cmd == b"QT" and self.streaming:  # connect (or close) starts with QT: a new link
                params = self.params
                self._new_link()
                self.params = params
            elif cmd == b"TM" and line[2:3] == b"1":
                self._tm_t0 = t
            elif cmd == b"TM" and line[2:3] == b"2":
                self.clock.add_round_trips(self._samples)
                self._samples = []
            elif cmd in (b"ME", b"MD", b"NE", b"ND") and len(line) >= 15 and self.params is not None:
                start, end, cluster = int(line[2:6]), int(line[6:10]), int(line[10:12])
                self.geometry = self.params.geometry(start, end, max(cluster, 1))
                self.prefix = line[:-2]
                self.streaming = True
            elif cmd == b"PP":
                self.clock = ClockMapper() if self.params is None else ClockMapper(default_latency=self.params.scan_time)

    def rx(self, t: float, data: bytes) -> list[Scan]:
        """Sensor -> host bytes read at host time ``t``; returns the scans they complete."""
        from drivers.hokuyo.client import SensorParams
        from drivers.hokuyo.clock import ClockMapper, RoundTrip
        from drivers.hokuyo.errors import ScipProtocolError
        from drivers.hokuyo.scip import InfoReply, ScanReply, TimeReply, distances_to_metres

        out = []
        for item in self.parser.feed(data):
            if isinstance(item, ScipProtocolError):
                self.corrupted += 1
                continue
            if isinstance(item, InfoReply) and item.command == "PP" and item.status == "00":
                self.params = SensorParams.from_pp(item.fields)
                self.clock = ClockMapper(default_latency=self.params.scan_time)
            elif isinstance(item, TimeReply) and self._tm_t0 is not None and item.status == "00":
                self._samples.append(RoundTrip(self._tm_t0, t, self.unwrap.unwrap(item.time_ms) / 1000.0))
                self._tm_t0 = None
            elif isinstance(item, ScanReply) and item.status == "99" and self.streaming \
                    and item.echo.raw.startswith(self.prefix) and self.params is not None:
                p = self.params
                ms = self.unwrap.unwrap(item.timestamp_ms)
                sensor = ms / 1000.0
                stamp = self.clock.observe(sensor, t)
                self.seq += 1
                out.append(Scan(stamp=stamp, ranges=distances_to_metres(item.distances, p.dmin, p.dmax),
                                intensities=None if item.intensities is None else item.intensities.astype(np.float64),
                                geometry=self.geometry, sensor_stamp=sensor, seq=self.seq))
        return out


class PioneerReplayDecoder:
    """The receive path of :class:`drivers.pioneer.client.PioneerClient` over recorded chunks.
    time_scale: the live client's (recorded in the metadata as ``base_time_scale``)."""

    def __init__(self, time_scale: float = 1.0) -> None:
        from drivers.pioneer.packets import PacketParser

        self.time_scale = time_scale
        self.parser = PacketParser()
        self.tracker = None
        self.model = None
        self.links = 0
        self.decode_errors = 0
        self._PacketParser = PacketParser

    def tx(self, t: float, data: bytes) -> None:
        from drivers.pioneer.packets import SYNC0, build_packet

        if data == build_packet(SYNC0):  # a (new) handshake: a fresh parser, the tracker survives
            self.parser = self._PacketParser()
            self.links += 1

    def rx(self, t: float, data: bytes) -> list[Odometry]:
        from drivers.pioneer.errors import DecodeError
        from drivers.pioneer.odometry import OdometryTracker, model_for
        from drivers.pioneer.packets import SIP_IDS, SYNC2
        from drivers.pioneer.sip import StandardSIP, decode_packet, decode_sync2

        out = []
        for pkt in self.parser.feed(data, t):
            if pkt.pid == SYNC2 and pkt.payload:
                try:
                    info = decode_sync2(pkt.payload)
                except DecodeError:
                    continue
                model = model_for(info.subclass, info.robot_class)
                if self.tracker is None or model != self.model:
                    self.tracker = OdometryTracker(model, time_scale=self.time_scale)
                self.model = model
                continue
            if pkt.pid not in SIP_IDS or self.tracker is None:
                continue
            try:
                msg = decode_packet(pkt)
            except DecodeError:
                self.decode_errors += 1
                continue
            if isinstance(msg, StandardSIP):
                out.append(self.tracker.update(msg, pkt.stamp if pkt.stamp is not None else t))
        return out


def _events(cap: Capture, device: str) -> Iterator[tuple[float, int, str, str, bytes]]:
    import json

    t0 = float(json.loads(cap.note or "{}").get("t0", 0.0))
    for i, c in enumerate(cap.chunks):
        yield (t0 + c.t, i, device, c.direction, c.data)


def iter_raw(path: str | Path) -> Iterator[Scan | Odometry]:
    """Scans and odometry decoded again from the raw bytes of a glassmap recording, in arrival order
    (host time of the reads), stamped like the live clients stamped them."""
    caps = read_captures(path)
    if "laser" not in caps:
        raise ReplayInputError(f"{path}: no raw laser bytes (/raw/laser); record with output.record_raw = true "
                               "or replay the decoded messages (--source messages)")
    from runtime.messages import TimeBase, as_recorded_odometry, as_recorded_scan
    from runtime.readers import read_metadata

    meta = read_metadata(path)
    tb = TimeBase(int(meta.get("time_offset_ns", "0")))
    laser = HokuyoReplayDecoder()
    base = PioneerReplayDecoder(float(meta.get("base_time_scale", "1")))
    streams = [_events(caps["laser"], "laser")]
    if "base" in caps:
        streams.append(_events(caps["base"], "base"))
    for t, _, dev, direction, data in heapq.merge(*streams):
        if direction == "tx":
            (laser if dev == "laser" else base).tx(t, data)
        elif dev == "laser":
            for scan in laser.rx(t, data):
                yield as_recorded_scan(scan, tb)
        else:
            for odom in base.rx(t, data):
                yield as_recorded_odometry(odom, tb)[0]
