"""Async client of the Pioneer 3-DX base (ARCOS/P2OS), over serial or TCP.

Use::

    async with PioneerClient.connect("serial:///dev/ttyUSB0", PioneerSettings(max_v=0.4),
                                     enable_motors=True) as base:
        async for odom in base.odometry():          # glassmap.types.Odometry, odom frame, m / rad
            await base.set_velocity(0.2, 0.0)      # m/s, rad/s; call again at least every command_timeout

or ``base = await PioneerClient.connect(url, settings)`` ... ``await base.close()``. The receive side
(packets, SIPs, odometry) is a :class:`~drivers.pioneer.session.PioneerSession`, shared with the raw replay.

What the client guarantees:
- Connect: SYNC0/1/2 with per-step timeouts and bounded retries; a robot still open from an earlier
  session (it answers with SIPs) gets CLOSE, a drain and a fresh handshake; on serial, a robot that does
  not answer at all also gets CLOSE at every baud rate once. Conversion factors from the reported subclass,
  OPEN, optional CONFIG read, optional switch to a higher baud rate, ENABLE on request, then the first SIP.
- Keep-alive: a packet at least every ``keepalive`` s (the current setpoint while moving, PULSE otherwise).
- Command timeout: when ``set_velocity`` is not called for ``command_timeout`` s the client stops the robot.
- Close (also on errors, cancellation, Ctrl-C when the caller's task is cancelled, and at interpreter exit
  as a synchronous last resort): VEL 0, RVEL 0, ENABLE 0, CLOSE, then the link is closed.
- Link loss (transport error, or no packet for ``sip_timeout`` s): reconnect with exponential back-off;
  the setpoint is reset to zero, so motion never resumes by itself (motors are re-enabled, at rest, if they
  were enabled). Taps (e.g. a CaptureRecorder) are attached to every new link.
- Odometry continues across reconnects (the controller keeps dead-reckoning while the host is away).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import math
import os
import time
import weakref
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlparse

from glassmap.types import Odometry

from drivers.clock_jit import warm_up as warm_up_clock
from drivers.connecting import Connecting
from drivers.errors import DriverError, TransportError
from drivers.pioneer.errors import (ClientClosedError, DecodeError, HandshakeError, HandshakeTimeout,
                                    LinkLostError)
from drivers.pioneer.odometry import CovarianceModel, PioneerModel
from drivers.pioneer.packets import (HOSTBAUD_CODES, SIP_IDS, SYNC0, SYNC1, SYNC2, Cmd, Packet, PacketType,
                                     build_packet, command)
from drivers.pioneer.session import BaseState, PioneerSession, PioneerStats
from drivers.pioneer.sip import ConfigPacket, EncoderPacket, StandardSIP, SyncReply, decode_config, decode_sync2
from drivers.transport import Tap, Transport, open_transport

log = logging.getLogger(__name__)

SERIAL_BAUDS = (9600, 19200, 38400, 57600, 115200)


@dataclass(frozen=True)
class PioneerSettings:
    """Client settings. Times in seconds (divided by ``time_scale``), speeds in m/s and rad/s.

    max_v, max_omega: limits applied to set_velocity (requests beyond are clamped).
    command_timeout: stop the robot when set_velocity was not called for this long (None: never).
    keepalive: send something at least this often (the robot's watchdog is 2 s).
    sip_timeout: no packet from the robot for this long means the link is lost.
    handshake_timeout: wait per handshake step; handshake_tries: full SYNC0..2 attempts before giving up.
    open_timeout: wait for the first SIP after OPEN (and for CONFIG when read_config).
    high_baud: serial only: switch to this speed after connecting (HOSTBAUD); None keeps the URL's speed.
    reconnect: reconnect after a link loss; backoff_initial / backoff_max: back-off between attempts.
    model: force the conversion factors ('p3dx' or 'p3dx-sh') instead of using the reported subclass.
    covariance: odometry noise model. time_scale: > 1 for emulators running faster than real time.
    odometry_queue: per-subscriber queue length (oldest dropped when a subscriber falls behind).
    """

    max_v: float = 0.5
    max_omega: float = math.radians(60.0)
    command_timeout: float | None = 0.6
    keepalive: float = 0.3
    sip_timeout: float = 1.5
    handshake_timeout: float = 0.5
    handshake_tries: int = 6
    open_timeout: float = 2.0
    read_config: bool = False
    high_baud: int | None = None
    reconnect: bool = True
    backoff_initial: float = 0.25
    backoff_max: float = 4.0
    model: str | None = None
    covariance: CovarianceModel = field(default_factory=CovarianceModel)
    time_scale: float = 1.0
    inter_byte_timeout: float = 0.5
    odometry_queue: int = 100

    def __post_init__(self) -> None:
        if self.max_v <= 0 or self.max_omega <= 0:
            raise ValueError("max_v and max_omega must be > 0")
        if self.time_scale <= 0:
            raise ValueError(f"time_scale must be > 0, got {self.time_scale}")
        if self.handshake_tries < 1:
            raise ValueError("handshake_tries must be >= 1")
        if self.command_timeout is not None and self.command_timeout <= 0:
            raise ValueError("command_timeout must be > 0 or None")
        if self.high_baud is not None and self.high_baud not in HOSTBAUD_CODES:
            raise ValueError(f"high_baud must be one of {sorted(HOSTBAUD_CODES)}, got {self.high_baud}")

    def host_seconds(self, robot_seconds: float) -> float:
        """A time in the robot's (emulated) seconds as host seconds: divided by time_scale."""
        return robot_seconds / self.time_scale


def _silence_hint(url: str) -> str:
    """What to check when the robot never answers, for this kind of link."""
    if url.startswith("tcp:"):
        return ("The TCP connection opened but nothing answered: is a Pioneer server (a simulator such as "
                "AMRISim, or a serial-to-TCP bridge on the robot) listening on that port, and is the bridge's "
                "serial side connected to the robot and powered on?")
    return ("Is the robot powered on, the cable in the controller's SERIAL port, the URL right "
            "(serial speed 9600 after power-up)?")


def _serial_url_with_baud(url: str, baud: int | None = None) -> str:
    """Serial URLs without ``baud`` get 9600 (the P3-DX power-up speed); ``baud`` overrides."""
    u = urlparse(url)
    if u.scheme != "serial":
        return url
    q = parse_qs(u.query)
    if baud is None:
        if "baud" in q:
            return url
        baud = 9600
    return f"serial://{u.path}?baud={baud}"


_live_clients: weakref.WeakSet[PioneerClient] = weakref.WeakSet()
_clock_warm = False


async def _warm_clock() -> None:
    """Load the SIP clock's compiled fit once per process (compile it, the first time on a machine), in a
    thread, rather than at its first fit in the event loop."""
    global _clock_warm
    if not _clock_warm:
        await asyncio.to_thread(warm_up_clock)
        _clock_warm = True


@atexit.register
def _stop_all_at_exit() -> None:  # last resort when the event loop died without close()
    for client in list(_live_clients):
        client._emergency_stop_sync()


class PioneerClient:
    """Async client of one Pioneer base. Create it with :meth:`connect`."""

    def __init__(self, url: str, settings: PioneerSettings | None = None, taps: Iterable[Tap] = ()) -> None:
        self.url = url
        self.settings = s = settings or PioneerSettings()
        self.taps: list[Tap] = list(taps)
        self.stats = PioneerStats()
        self.session = PioneerSession(self.stats, model=s.model, covariance=s.covariance, time_scale=s.time_scale,
                                      inter_byte_timeout=s.inter_byte_timeout, name=url)
        self.odometry_callbacks: list[Callable[[Odometry], None]] = []
        self._transport: Transport | None = None
        self._pending: list[Packet] = []  # packets read during the handshake, not yet handled
        self._held: list[Packet] = []  # packets read while waiting for CONFIG
        self._subscribers: set[asyncio.Queue[Odometry | None]] = set()
        self._setpoint = (0, 0)  # (VEL mm/s, RVEL deg/s) last sent by the caller
        self._last_cmd = 0.0
        self._last_tx = 0.0
        self._last_rx = 0.0
        self._link_up = False
        self._link_event = asyncio.Event()
        self._first_sip = asyncio.Event()
        self._motors_wanted = False
        self._closing = False
        self._closed = False
        self._failure: BaseException | None = None
        self._send_lock = asyncio.Lock()
        self._tasks: list[asyncio.Task] = []
        self._reader_task: asyncio.Task | None = None
        self._closer: asyncio.Task | None = None  # closes a transport the watchdog found dead

    # -- construction ----------------------------------------------------------------------------------
    @classmethod
    def connect(cls, url: str, settings: PioneerSettings | None = None, *, taps: Iterable[Tap] = (),
                enable_motors: bool = False) -> Connecting[PioneerClient]:
        """Connect to the base at ``url`` (``serial:///dev/ttyUSB0[?baud=9600]`` or ``tcp://host:8101``).

        Await the result, or ``async with`` it to have the client closed (robot stopped) on exit. Raises
        HandshakeError (robot does not answer or answers wrongly), TransportError (cannot open the link),
        ValueError (bad URL).
        """

        async def factory() -> PioneerClient:
            client = cls(url, settings, taps)
            try:
                await client._start(enable_motors)
            except BaseException:
                await client.close()
                raise
            return client

        return Connecting(factory)

    async def _start(self, enable_motors: bool) -> None:
        await _warm_clock()  # before the link opens: nothing waits on the event loop yet
        await self._open_link()
        self._reader_task = asyncio.create_task(self._supervise(), name="pioneer-link")
        self._tasks = [self._reader_task, asyncio.create_task(self._control_loop(), name="pioneer-control")]
        _live_clients.add(self)
        try:
            await asyncio.wait_for(self._first_sip.wait(), self.settings.host_seconds(self.settings.open_timeout))
        except asyncio.TimeoutError:
            raise HandshakeError(
                f"{self.url}: robot accepted OPEN but sent no SIP within {self.settings.open_timeout:.1f} s") from None
        if enable_motors:
            await self.enable_motors(True)

    # -- public API ------------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while the link is up (False during a reconnect and after close)."""
        return self._link_up and not self._closed

    @property
    def state(self) -> BaseState | None:
        """Battery, motors, e-stop, stall, bumpers, sonar from the latest SIP (None before the first)."""
        return self.session.state

    @property
    def info(self) -> SyncReply | None:
        """The robot's SYNC2 reply (name, class, subclass) of the current or last link."""
        return self.session.info

    @property
    def model(self) -> PioneerModel | None:
        """The conversion factors in use."""
        return self.session.model

    @property
    def config(self) -> ConfigPacket | None:
        """The newest CONFIG packet (``read_config``, or asked for by a tool)."""
        return self.session.config

    @property
    def encoders(self) -> EncoderPacket | None:
        """The newest ENCODER packet (see :meth:`request_encoders`)."""
        return self.session.encoders

    @property
    def last_sip(self) -> StandardSIP | None:
        return self.session.last_sip

    @property
    def latest(self) -> Odometry | None:
        """The newest odometry (for polling)."""
        return self.session.latest

    @property
    def setpoint(self) -> tuple[float, float]:
        """The velocity currently commanded (m/s, rad/s) after clamping and rounding."""
        return self._setpoint[0] / 1000.0, math.radians(self._setpoint[1])

    def odometry(self) -> AsyncIterator[Odometry]:
        """Async iterator over odometry, one per SIP, from now on; ends when the client closes.

        Each subscriber has its own bounded queue; a subscriber that falls behind loses the oldest poses
        (counted in ``stats.odometry_dropped``). ``latest`` holds the newest pose for polling. To leave
        early, wrap it in ``contextlib.aclosing`` (the queue is released at once instead of at collection).
        """
        q: asyncio.Queue[Odometry | None] = asyncio.Queue(maxsize=self.settings.odometry_queue)
        self._subscribers.add(q)
        return self._iterate(q)

    async def _iterate(self, q: asyncio.Queue[Odometry | None]) -> AsyncIterator[Odometry]:
        try:
            while not self._closed:
                item = await q.get()
                if item is None:
                    break
                yield item
        finally:
            self._subscribers.discard(q)
        if self._failure is not None:
            raise self._failure

    async def set_velocity(self, v: float, omega: float) -> None:
        """Command forward speed ``v`` (m/s) and turn rate ``omega`` (rad/s, CCW +), clamped to the limits.

        Repeat at least every ``command_timeout`` s or the client stops the robot. Raises LinkLostError
        while reconnecting, ClientClosedError after close, ValueError for non-finite values.
        """
        if not (math.isfinite(v) and math.isfinite(omega)):
            raise ValueError(f"velocity must be finite, got v={v}, omega={omega}")
        s = self.settings
        v = max(-s.max_v, min(s.max_v, v))
        omega = max(-s.max_omega, min(s.max_omega, omega))
        sp = (int(round(v * 1000.0)), int(round(math.degrees(omega))))
        self._check_usable()
        self._setpoint = sp
        self._last_cmd = time.monotonic()
        await self._send_setpoint()

    async def stop(self) -> None:
        """Velocity zero (motors stay enabled)."""
        self._check_usable()
        self._setpoint = (0, 0)
        self._last_cmd = time.monotonic()
        await self._send_setpoint()

    async def estop(self) -> None:
        """Emergency stop (ESTOP: the controller stops at once, overriding deceleration)."""
        self._setpoint = (0, 0)
        self._check_usable()
        await self._send(command(Cmd.ESTOP))

    async def enable_motors(self, on: bool = True) -> None:
        """ENABLE 1/0. Disabling also zeroes the setpoint. Re-enabled at rest after a reconnect."""
        self._check_usable()
        self._motors_wanted = on
        if not on:
            self._setpoint = (0, 0)
        await self._send(command(Cmd.ENABLE, 1 if on else 0))

    async def request_encoders(self, mode: int = 2) -> None:
        """ENCODER packets: 0 off, 1 one packet, 2 continuous; the newest is in ``encoders``."""
        if mode not in (0, 1, 2):
            raise ValueError(f"encoder mode must be 0, 1 or 2, got {mode}")
        self._check_usable()
        await self._send(command(Cmd.ENCODER, mode))

    async def send_command(self, cmd: int, arg: int | str | bytes | None = None) -> None:
        """Send any ARCOS command (for tools; motion should go through set_velocity)."""
        self._check_usable()
        await self._send(command(cmd, arg))

    async def wait_connected(self, timeout: float | None = None) -> None:
        """Wait until the link is up (after a reconnect). Raises asyncio.TimeoutError or the link failure."""
        async def _wait() -> None:
            while not self.connected:
                if self._closed:
                    raise self._failure or ClientClosedError(f"{self.url}: client closed")
                self._link_event.clear()
                await self._link_event.wait()
        await asyncio.wait_for(_wait(), timeout)

    async def close(self) -> None:
        """Stop the robot and close: VEL 0, RVEL 0, ENABLE 0, CLOSE, then the link. Safe to call twice."""
        if self._closing:
            return
        self._closing = True
        current = asyncio.current_task()
        for task in self._tasks:
            if task is not current:
                task.cancel()
        for task in self._tasks:
            if task is not current:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        t = self._transport
        if t is not None and not t.closed:
            try:
                await asyncio.wait_for(self._write_stop_sequence(t), 1.0)
            except (DriverError, OSError, asyncio.TimeoutError) as exc:
                log.warning("%s: could not send the stop sequence on close (%s)", self.url, exc)
            await t.close()
        self._end_streams()

    async def __aenter__(self) -> PioneerClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- sending ---------------------------------------------------------------------------------------
    def _check_usable(self) -> None:
        if self._closed or self._closing:
            raise ClientClosedError(f"{self.url}: client is closed")
        if not self._link_up:
            raise LinkLostError(f"{self.url}: link to the robot is down (reconnecting); command not sent")

    async def _send(self, *packets: bytes) -> None:
        t = self._transport
        if t is None or not self._link_up:
            raise LinkLostError(f"{self.url}: link to the robot is down; command not sent")
        async with self._send_lock:
            try:
                await t.write(b"".join(packets))
            except TransportError as exc:
                self._link_lost(exc)
                raise LinkLostError(f"{self.url}: link lost while sending ({exc})") from exc
        self.stats.tx_packets += len(packets)
        self._last_tx = time.monotonic()

    async def _send_setpoint(self) -> None:
        v, w = self._setpoint
        await self._send(command(Cmd.VEL, v), command(Cmd.RVEL, w))

    async def _write_stop_sequence(self, t: Transport) -> None:
        await t.write(command(Cmd.VEL, 0) + command(Cmd.RVEL, 0) + command(Cmd.ENABLE, 0) + command(Cmd.CLOSE))
        self._setpoint = (0, 0)

    def _emergency_stop_sync(self) -> None:
        """Write the stop sequence synchronously to the OS handle (at interpreter exit, loop gone)."""
        if self._closed or self._transport is None or self._transport.closed:
            return
        data = command(Cmd.VEL, 0) + command(Cmd.RVEL, 0) + command(Cmd.ENABLE, 0) + command(Cmd.CLOSE)
        with contextlib.suppress(Exception):
            writer = getattr(self._transport, "_writer", None)
            tr = getattr(writer, "transport", None)
            serial = getattr(tr, "serial", None)
            if serial is not None:
                serial.write(data)
                serial.flush()
                return
            sock = tr.get_extra_info("socket") if tr is not None else None
            if sock is not None:
                os.write(sock.fileno(), data)  # a few dozen bytes: fits the socket buffer

    # -- link management -------------------------------------------------------------------------------
    async def _open_link(self) -> None:
        """Open the transport, handshake, OPEN, (CONFIG), (HOSTBAUD). Raises on failure."""
        s = self.settings
        transport = await open_transport(_serial_url_with_baud(self.url), timeout=s.host_seconds(5.0))
        for tap in self.taps:
            transport.taps.append(tap)
        self.session.new_link()
        self._pending = []
        try:
            info = await self._handshake(transport)
            self.session.connected(info)
            await transport.write(command(Cmd.OPEN))
            if s.read_config:
                await transport.write(command(Cmd.CONFIG))
                self.session.config = await self._await_config(transport)
            if s.high_baud is not None and transport.url.startswith("serial:"):
                await self._switch_baud(transport, s.high_baud)
        except BaseException:
            self.session.end_link()
            await transport.close()
            raise
        self._transport = transport
        now = time.monotonic()
        self._last_rx = self._last_tx = self._last_cmd = now
        self._setpoint = (0, 0)
        self._link_up = True
        self._link_event.set()
        log.info("%s: connected to %s (%s %s)", self.url, info.name, info.robot_class, info.subclass)

    async def _recv(self, transport: Transport, timeout: float) -> Packet | None:
        """Next packet within ``timeout`` s, or None."""
        deadline = time.monotonic() + timeout
        while not self._pending:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                data = await asyncio.wait_for(transport.read(), left)
            except asyncio.TimeoutError:
                return None
            self._pending.extend(self.session.feed(data, transport.last_read_time))  # the taps' time
        return self._pending.pop(0)

    async def _drain(self, transport: Transport, quiet: float, limit: float) -> None:
        """Read and discard until nothing arrives for ``quiet`` s (at most ``limit`` s)."""
        end = time.monotonic() + limit
        self._pending.clear()
        while time.monotonic() < end:
            if await self._recv(transport, min(quiet, max(0.0, end - time.monotonic()))) is None:
                return
            self._pending.clear()

    async def _handshake(self, transport: Transport) -> SyncReply:
        s = self.settings
        step_timeout = s.host_seconds(s.handshake_timeout)
        heard_anything = False
        baud_cycled = False
        for attempt in range(s.handshake_tries):
            if attempt:
                self.stats.handshake_retries += 1
                if (not heard_anything and not baud_cycled and transport.url.startswith("serial:")
                        and attempt >= 2):
                    baud_cycled = True
                    await self._close_at_every_baud(transport)
            step = 0
            await transport.write(build_packet(SYNC0))
            while True:
                pkt = await self._recv(transport, step_timeout)
                if pkt is None:
                    log.debug("%s: no answer to SYNC%d (attempt %d)", self.url, step, attempt + 1)
                    break
                heard_anything = True
                if pkt.pid in SIP_IDS:
                    log.info("%s: robot still open from an earlier session: CLOSE and start again", self.url)
                    self.stats.still_open_recoveries += 1
                    await transport.write(command(Cmd.CLOSE))
                    await self._drain(transport, quiet=2 * step_timeout, limit=s.host_seconds(3.0))
                    break
                if pkt.pid == step and step < 2 and not pkt.payload:
                    step += 1
                    await transport.write(build_packet((SYNC0, SYNC1, SYNC2)[step]))
                elif pkt.pid == SYNC2 and step == 2:
                    try:
                        return decode_sync2(pkt.payload)
                    except DecodeError as exc:
                        log.warning("%s: bad SYNC2 reply (%s); retrying", self.url, exc)
                        break
                # anything else (stale echoes, unknown packets) is ignored
        if not heard_anything:
            raise HandshakeTimeout(
                f"{self.url}: no answer to SYNC0 after {s.handshake_tries} tries of {s.handshake_timeout:.2f} s. "
                + _silence_hint(transport.url))
        raise HandshakeError(
            f"{self.url}: handshake failed after {s.handshake_tries} tries (the robot answers but the SYNC "
            "sequence never completed; line noise, or another program on the port?)")

    async def _close_at_every_baud(self, transport: Transport) -> None:
        """A robot left at another speed may need CLOSE at that speed before it answers again."""
        home = _baud_of(transport.url)
        for baud in SERIAL_BAUDS:
            with contextlib.suppress(TransportError):
                await transport.set_baudrate(baud)
                await transport.write(command(Cmd.CLOSE))
                await asyncio.sleep(0.05)
        with contextlib.suppress(TransportError):
            await transport.set_baudrate(home)

    async def _await_config(self, transport: Transport) -> ConfigPacket | None:
        s = self.settings
        deadline = time.monotonic() + s.host_seconds(s.open_timeout)
        while (left := deadline - time.monotonic()) > 0:
            pkt = await self._recv(transport, left)
            if pkt is None:
                break
            if pkt.pid == PacketType.CONFIG:
                try:
                    return decode_config(pkt.payload)
                except DecodeError as exc:
                    log.warning("%s: bad CONFIG packet (%s)", self.url, exc)
                    return None
            self._held.append(pkt)
        log.warning("%s: no CONFIG packet within %.1f s; continuing without it", self.url, s.open_timeout)
        return None

    async def _switch_baud(self, transport: Transport, baud: int) -> None:
        await transport.write(command(Cmd.HOSTBAUD, HOSTBAUD_CODES[baud]))
        await asyncio.sleep(0.05)
        await transport.set_baudrate(baud)
        # self.url keeps the power-up speed: after a link loss the robot may be back at 9600, and one still
        # at `baud` is reached by the CLOSE-at-every-speed step of the handshake.
        log.info("%s: switched to %d baud", self.url, baud)

    def _link_lost(self, exc: BaseException) -> None:
        if not self._link_up:
            return
        log.warning("%s: link lost (%s)", self.url, exc)
        self._link_up = False
        self._setpoint = (0, 0)
        self.stats.link_losses += 1
        if self._reader_task is not None and self._reader_task is not asyncio.current_task():
            t = self._transport
            if t is not None:  # the reader task sees the closed link and reconnects
                self._closer = asyncio.get_running_loop().create_task(t.close())

    async def _supervise(self) -> None:
        """Read packets while the link is up; on a loss, reconnect with back-off (if enabled)."""
        try:
            await self._supervise_links()
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug must not leave the robot driving with nobody listening
            log.exception("%s: link supervisor failed; stopping the robot", self.url)
            self._failure = exc
            t = self._transport
            if t is not None and not t.closed:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(self._write_stop_sequence(t), 1.0)
                await t.close()
            self._end_streams()

    def _end_streams(self) -> None:
        self._link_up = False
        self._closed = True
        _live_clients.discard(self)
        self._link_event.set()
        for q in list(self._subscribers):
            self._offer(q, None)

    async def _supervise_links(self) -> None:
        s = self.settings
        while not self._closing:
            t = self._transport
            if t is None:
                raise RuntimeError(f"{self.url}: link supervisor started without a link")
            backlog, self._held, self._pending = self._held + self._pending, [], []
            for pkt in backlog:
                self._on_packet(pkt)
            try:
                while True:
                    data = await t.read()
                    for pkt in self.session.feed(data, t.last_read_time):  # the time the taps recorded
                        self._on_packet(pkt)
            except TransportError as exc:
                self._link_lost(exc)
                await t.close()
            if self._closing:
                return
            self.session.end_link()
            if not s.reconnect:
                self._failure = LinkLostError(f"{self.url}: link lost and reconnect is disabled")
                self._end_streams()
                return
            delay = s.host_seconds(s.backoff_initial)
            while not self._closing:
                await asyncio.sleep(delay)
                try:
                    await self._open_link()
                except (DriverError, OSError, ValueError) as exc:
                    log.info("%s: reconnect failed (%s); next try in %.2f s", self.url, exc, delay)
                    delay = min(2 * delay, s.host_seconds(s.backoff_max))
                    continue
                self.stats.reconnects += 1
                if self._motors_wanted:
                    with contextlib.suppress(DriverError):
                        await self._send(command(Cmd.ENABLE, 1))  # at rest: the setpoint is zero
                break

    async def _control_loop(self) -> None:
        """Keep-alive, command timeout and the SIP watchdog."""
        s = self.settings
        periods = [s.keepalive, s.sip_timeout] + ([s.command_timeout] if s.command_timeout else [])
        tick = s.host_seconds(min(periods) / 6.0)
        while not self._closing:
            await asyncio.sleep(tick)
            if not self._link_up:
                continue
            now = time.monotonic()
            try:
                if now - self._last_rx > s.host_seconds(s.sip_timeout):
                    self._link_lost(TransportError(f"no packet from the robot for {s.sip_timeout:.1f} s"))
                    continue
                if (s.command_timeout is not None and self._setpoint != (0, 0)
                        and now - self._last_cmd > s.host_seconds(s.command_timeout)):
                    log.warning("%s: no velocity command for %.2f s: stopping the robot", self.url,
                                s.command_timeout)
                    self.stats.command_timeouts += 1
                    self._setpoint = (0, 0)
                    await self._send_setpoint()
                elif now - self._last_tx >= s.host_seconds(s.keepalive):
                    self.stats.keepalives += 1
                    if self._setpoint != (0, 0):
                        await self._send_setpoint()
                    else:
                        await self._send(command(Cmd.PULSE))
            except LinkLostError:
                continue

    # -- receiving -------------------------------------------------------------------------------------
    def _on_packet(self, pkt: Packet) -> None:
        self._last_rx = time.monotonic()
        odom = self.session.handle(pkt, self._last_rx)
        if odom is None:
            return
        self._first_sip.set()
        for q in list(self._subscribers):
            self._offer(q, odom)
        for cb in list(self.odometry_callbacks):
            try:
                cb(odom)
            except Exception:
                log.exception("%s: odometry callback failed", self.url)

    def _offer(self, q: asyncio.Queue[Odometry | None], item: Odometry | None) -> None:
        while True:
            try:
                q.put_nowait(item)
                return
            except asyncio.QueueFull:
                q.get_nowait()
                self.stats.odometry_dropped += 1


def _baud_of(url: str) -> int:
    q = parse_qs(urlparse(url).query)
    try:
        return int(q.get("baud", ["9600"])[0])
    except ValueError:
        return 9600
