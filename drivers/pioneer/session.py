"""The receive side of a Pioneer (ARCOS/P2OS) link (sans-IO), shared by the live client and the raw replay.

A :class:`PioneerSession` is fed the bytes the host read with the host time (s) of each read. It keeps the
per-link packet parser, the robot model from the handshake's SYNC2 reply, and the odometry tracker (which
outlives a link: the controller keeps dead-reckoning while the host is away), and turns SIPs into
``glassmap.types.Odometry`` and a :class:`BaseState` (stamped on the SIP cycle by ``drivers.pioneer.sip_clock``),
counting what it discards in a :class:`PioneerStats`. It never reads a clock and never touches a port: the client feeds it live bytes
(and drives the handshake with the packets it returns), ``runtime.raw_replay`` feeds it recorded ones.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from drivers.pioneer.errors import DecodeError
from drivers.pioneer.odometry import CovarianceModel, OdometryTracker, PioneerModel, model_for
from drivers.pioneer.packets import SIP_IDS, Packet, PacketParser, ParserStats
from drivers.pioneer.sip_clock import SipClock
from drivers.pioneer.sip import (ConfigPacket, EncoderPacket, StandardSIP, SyncReply, UnknownPacket,
                                 decode_packet)
from glassmap.types import Odometry

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BaseState:
    """Latest state of the base from the SIPs. stamp: host time (s); battery in volts; sonar in metres."""

    stamp: float
    battery_volts: float
    motors_enabled: bool
    estop: bool
    moving: bool
    left_stall: bool
    right_stall: bool
    front_bumpers: int
    rear_bumpers: int
    sonar: dict[int, float]

    @property
    def stalled(self) -> bool:
        return self.left_stall or self.right_stall

    @property
    def bumped(self) -> bool:
        return bool(self.front_bumpers or self.rear_bumpers)


@dataclass
class PioneerStats:
    """Counters since the client was created (over all links).

    tx_packets counts commands sent on open links (handshake packets are not counted); keepalives the
    packets sent only to keep the robot's watchdog quiet; command_timeouts the stops the client made because
    set_velocity went quiet; still_open_recoveries the handshakes that found the robot open and closed it.
    """

    sips: int = 0
    packets: int = 0
    unknown_packets: int = 0
    decode_errors: int = 0
    bad_checksum: int = 0
    bad_length: int = 0
    dropped_bytes: int = 0
    parser_timeouts: int = 0
    tx_packets: int = 0
    keepalives: int = 0
    command_timeouts: int = 0
    link_losses: int = 0
    reconnects: int = 0
    handshake_retries: int = 0
    still_open_recoveries: int = 0
    odometry_dropped: int = 0


class PioneerSession:
    """Receive state of a Pioneer link.

    model: force the conversion factors ('p3dx', 'p3dx-sh') instead of the reported subclass; covariance:
    odometry noise model; time_scale: > 1 for emulators running faster than real time; inter_byte_timeout:
    a partial packet older than this (s) is given up.
    """

    def __init__(self, stats: PioneerStats | None = None, *, model: str | None = None,
                 covariance: CovarianceModel | None = None, time_scale: float = 1.0,
                 inter_byte_timeout: float | None = 0.5, name: str = "pioneer") -> None:
        self.stats = stats if stats is not None else PioneerStats()
        self.name = name
        self.forced_model = model
        self.covariance = covariance or CovarianceModel()
        self.time_scale = time_scale
        self.inter_byte_timeout = inter_byte_timeout
        self.info: SyncReply | None = None
        self.model: PioneerModel | None = None
        self.config: ConfigPacket | None = None
        self.encoders: EncoderPacket | None = None
        self.last_sip: StandardSIP | None = None
        self.state: BaseState | None = None
        self.latest: Odometry | None = None
        self.links = 0
        self._sonar: dict[int, float] = {}
        self.tracker: OdometryTracker | None = None
        self._parser: PacketParser | None = None
        self._parser_totals = ParserStats()
        self.sip_clock = SipClock(time_scale=time_scale)
        self._queued: dict[int, int] = {}  # id(SIP packet) -> SIPs after it in the same read

    # -- links ------------------------------------------------------------------------------------------
    def new_link(self) -> None:
        """A new connection (a new handshake): a fresh parser; the odometry tracker carries over."""
        self.end_link()
        self._parser = PacketParser(inter_byte_timeout=self.inter_byte_timeout)
        self.sip_clock.reset()
        self.links += 1

    def end_link(self) -> None:
        """The link is gone: keep its parser's counters."""
        p = self._parser
        if p is None:
            return
        tot = self._parser_totals
        for name in ("bytes_in", "packets", "dropped_bytes", "bad_checksum", "bad_length", "timeouts"):
            setattr(tot, name, getattr(tot, name) + getattr(p.stats, name))
        self._parser = None
        self._sync_parser_stats()

    def connected(self, info: SyncReply) -> PioneerModel:
        """The handshake's SYNC2 reply: choose the conversion factors; a different robot re-anchors odometry."""
        model = model_for(self.forced_model or info.subclass, info.robot_class)
        if self.model is not None and model != self.model:
            log.warning("%s: robot changed from %s to %s; odometry re-anchors", self.name,
                        self.model.subclass, model.subclass)
            self.tracker = None
        self.info, self.model = info, model
        if self.tracker is None:
            self.tracker = OdometryTracker(model, self.covariance, self.time_scale)
        return model

    # -- bytes in ---------------------------------------------------------------------------------------
    def feed(self, data: bytes, t: float) -> list[Packet]:
        """Bytes read at host time ``t``: the complete packets (for the handshake, or for :meth:`handle`)."""
        if self._parser is None:
            self.new_link()
        packets = self._parser.feed(data, t)
        self._sync_parser_stats()
        sips = [p for p in packets if p.pid in SIP_IDS]
        self._queued = {id(p): len(sips) - 1 - i for i, p in enumerate(sips)}
        return packets

    def handle(self, pkt: Packet, t: float) -> Odometry | None:
        """Decode a packet of an open link (read at host time ``t``); the odometry if it was a SIP."""
        self.stats.packets += 1
        try:
            msg = decode_packet(pkt)
        except DecodeError as exc:
            self.stats.decode_errors += 1
            log.debug("%s: %s", self.name, exc)
            return None
        if isinstance(msg, StandardSIP):
            arrival = pkt.stamp if pkt.stamp is not None else t
            cycles = self.tracker.cycles_since_last(msg, self.sip_clock.cycle) if self.tracker is not None else None
            return self._on_sip(msg, self.sip_clock.stamp(arrival, self._queued.pop(id(pkt), 0), cycles))
        if isinstance(msg, EncoderPacket):
            self.encoders = msg
        elif isinstance(msg, ConfigPacket):
            self.config = msg
            self.sip_clock.set_cycle(msg.sip_cycle / 1000.0)
        elif isinstance(msg, UnknownPacket):
            self.stats.unknown_packets += 1
        return None

    def _on_sip(self, sip: StandardSIP, stamp: float) -> Odometry | None:
        """A SIP stamped (host s) on the SIP cycle by ``sip_clock``."""
        if self.tracker is None or self.model is None:  # a SIP before any handshake: no model to read it
            self.stats.unknown_packets += 1
            return None
        self.stats.sips += 1
        self.last_sip = sip
        for idx, rng in sip.sonar:
            self._sonar[idx] = rng * self.model.range_conv / 1000.0
        self.state = BaseState(stamp=stamp, battery_volts=sip.battery_volts, motors_enabled=sip.motors_enabled,
                               estop=sip.estop, moving=sip.moving, left_stall=sip.left_stall,
                               right_stall=sip.right_stall, front_bumpers=sip.front_bumpers,
                               rear_bumpers=sip.rear_bumpers, sonar=dict(self._sonar))
        self.latest = self.tracker.update(sip, stamp)
        return self.latest

    def _sync_parser_stats(self) -> None:
        tot, cur = self._parser_totals, (self._parser.stats if self._parser is not None else ParserStats())
        st = self.stats
        st.bad_checksum = tot.bad_checksum + cur.bad_checksum
        st.bad_length = tot.bad_length + cur.bad_length
        st.dropped_bytes = tot.dropped_bytes + cur.dropped_bytes
        st.parser_timeouts = tot.timeouts + cur.timeouts


__all__ = ["BaseState", "PioneerSession", "PioneerStats"]
