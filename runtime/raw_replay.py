"""Replay of the raw device bytes of a recording through the drivers' own receive sessions.

The recorded chunks of each link (/raw/laser, /raw/base: both directions, with the host time each read or
write happened) are fed, in order and with their recorded times, to the very objects the live clients
feed: :class:`drivers.hokuyo.session.HokuyoSession` (SCIP parser, PP parameters, stamp unwrapping, TM1
round trips, clock mapping, multi-echo) and :class:`drivers.pioneer.session.PioneerSession` (packet
parser, SYNC2 model, odometry tracker). What this module adds is only what a live client knows without
reading it from the bytes: where a new connection starts and which packets arrive during a handshake
(see :class:`HokuyoReplay` and :class:`PioneerReplay`).

The clients give their sessions the very host times the transport's taps record (``last_read_time`` of each
read, the time noted for each command write), so replayed stamps agree with the live ones up to the
recording's time resolution, however loaded the machine was.

Why not the client classes themselves over a fake link? Their handshakes wait on real timeouts and they
read the clock themselves; feeding recorded chunks to their receive sessions is exact and as fast as the
decoder.
"""

from __future__ import annotations

import heapq
import itertools
import logging
from collections import deque
from collections.abc import Iterator, Sequence
from pathlib import Path

from drivers.hokuyo.session import HokuyoSession
from drivers.pioneer.errors import DecodeError
from drivers.pioneer.packets import SYNC0, SYNC1, SYNC2, Cmd, build_packet, command
from drivers.pioneer.session import PioneerSession
from drivers.pioneer.sip import decode_sync2
from glassmap.types import Odometry, Scan
from runtime.readers import RawChunk, ReplayInputError, iter_raw_chunks

log = logging.getLogger(__name__)

_CLOSE = command(Cmd.CLOSE)
_SYNC0, _SYNC1 = build_packet(SYNC0), build_packet(SYNC1)


class HokuyoReplay:
    """Recorded laser chunks through a :class:`HokuyoSession`; a QT sent while a stream runs starts a new
    link (the client's connect, reconnect and close all begin with QT)."""

    def __init__(self) -> None:
        self.session = HokuyoSession(name="raw laser")

    def tx(self, t: float, data: bytes) -> None:
        """Host -> sensor bytes written at host time ``t``."""
        if self.session.streaming and data.lstrip().startswith(b"QT"):
            self.session.new_link()
        self.session.sent(t, data)

    def rx(self, t: float, data: bytes) -> list[Scan]:
        """Sensor -> host bytes read at host time ``t``; returns the scans they complete."""
        return self.session.received(t, data)[0]


class PioneerReplay:
    """Recorded base chunks through a :class:`PioneerSession`.

    The recording does not mark connections, and a SYNC0 written by the host is byte for byte a PULSE
    keep-alive. A handshake is therefore recognised (1) from the host's writes (``tx_chunks``, all of them,
    or the next write given to :meth:`tx`): a SYNC0 followed by SYNC1 (the robot answered) or by a lone
    CLOSE (the robot was still open); (2) from the robot's side: a SYNC0 echo, which a robot sends only in a
    handshake; (3) a lone CLOSE written while open. From a handshake's start to the robot's SYNC2 reply
    packets are not handled, as on a live link; a handshake after an open link starts a new link (a
    reconnection).
    time_scale / model: the live client's (recorded in the metadata as ``base_time_scale``, ``base_model``).
    """

    def __init__(self, time_scale: float = 1.0, model: str | None = None,
                 tx_chunks: Sequence[bytes] | None = None) -> None:
        self.session = PioneerSession(name="raw base", time_scale=time_scale, model=model)
        self.handshaking = True
        txs = list(tx_chunks or ())
        self._starts = {i for i, d in enumerate(txs[:-1]) if d == _SYNC0 and txs[i + 1] in (_SYNC1, _CLOSE)}
        self._n_tx = 0

    def tx(self, t: float, data: bytes, next_tx: bytes | None = None) -> None:
        """Host -> robot bytes written at host time ``t``; ``next_tx``: the host's next write, when the
        writes come one at a time instead of as ``tx_chunks``."""
        start = self._n_tx in self._starts or (data == _SYNC0 and next_tx in (_SYNC1, _CLOSE))
        if data == _CLOSE or start:
            self._handshake()
        self._n_tx += 1

    def _handshake(self) -> None:
        if not self.handshaking and self.session.info is not None:  # an open link ends: a new one starts
            self.session.new_link()
        self.handshaking = True

    def rx(self, t: float, data: bytes) -> list[Odometry]:
        out = []
        for pkt in self.session.feed(data, t):
            if pkt.pid == SYNC2 and pkt.payload:
                try:
                    self.session.connected(decode_sync2(pkt.payload))
                except DecodeError:
                    continue  # the client retries the handshake
                self.handshaking = False
            elif pkt.pid == SYNC0 and not pkt.payload:
                self._handshake()
            elif not self.handshaking and pkt.pid not in (SYNC0, SYNC1, SYNC2):
                if (odom := self.session.handle(pkt, t)) is not None:
                    out.append(odom)
        return out


class _Demux:
    """One pass over a recording's raw chunks split into a stream per device; reading goes only as far ahead
    as a stream's consumer needs (the other devices' chunks read meanwhile wait in their queues)."""

    def __init__(self, chunks: Iterator[RawChunk], devices: Sequence[str]) -> None:
        self._chunks = chunks
        self._queues: dict[str, deque[RawChunk]] = {d: deque() for d in devices}

    def _pull(self) -> bool:
        for c in self._chunks:
            if (q := self._queues.get(c.device)) is not None:
                q.append(c)
                return True
        return False

    def stream(self, device: str) -> Iterator[RawChunk]:
        q = self._queues[device]
        while q or self._pull():
            if q:
                yield q.popleft()


Event = tuple[float, int, str, str, bytes, "bytes | None"]  # host time, index, device, direction, data, next tx


def _events(chunks: Iterator[RawChunk]) -> Iterator[Event]:
    """A device's chunks as merge keys: host time as the capture format gives it back (first chunk's time +
    time since the first chunk), then the chunk's index; next tx: None (see :func:`_with_next_tx`)."""
    t0 = None
    for i, c in enumerate(chunks):
        t0 = c.host_time if t0 is None else t0
        yield (t0 + (c.host_time - t0), i, c.device, c.direction, c.data, None)


def _with_next_tx(events: Iterator[Event]) -> Iterator[Event]:
    """``events`` with each tx event carrying the data of the device's next tx (None for the last), which
    :meth:`PioneerReplay.tx` needs to recognise a handshake; the rx events after a tx wait with it."""
    held: list[Event] = []
    for ev in events:
        if ev[3] == "tx" and held:
            yield held[0][:5] + (ev[4],)
            yield from held[1:]
            held = []
        if ev[3] == "tx" or held:
            held.append(ev)
        else:
            yield ev
    yield from held


def iter_raw(path: str | Path) -> Iterator[Scan | Odometry]:
    """Scans and odometry decoded again from the raw bytes of a glassmap recording, in arrival order
    (host time of the reads), stamped like the live clients stamped them. The recording is read once, as
    the replay goes (not held in memory)."""
    from runtime.messages import TimeBase, as_recorded_odometry, as_recorded_scan
    from runtime.readers import read_metadata

    demux = _Demux(iter_raw_chunks(path), ("laser", "base"))
    laser_events = _events(demux.stream("laser"))
    first = next(laser_events, None)
    if first is None:
        raise ReplayInputError(f"{path}: no raw laser bytes (/raw/laser); record with output.record_raw = true "
                               "or replay the decoded messages (--source messages)")
    meta = read_metadata(path)
    tb = TimeBase(int(meta.get("time_offset_ns", "0")))
    laser = HokuyoReplay()
    base = PioneerReplay(float(meta.get("base_time_scale", "1")), meta.get("base_model") or None)
    streams = (itertools.chain((first,), laser_events), _with_next_tx(_events(demux.stream("base"))))
    for t, _, dev, direction, data, next_tx in heapq.merge(*streams):
        if direction == "tx":
            if dev == "laser":
                laser.tx(t, data)
            else:
                base.tx(t, data, next_tx)
        elif dev == "laser":
            for scan in laser.rx(t, data):
                yield as_recorded_scan(scan, tb)
        else:
            for odom in base.rx(t, data):
                yield as_recorded_odometry(odom, tb)[0]
