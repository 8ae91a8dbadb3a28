"""An emulated Pioneer 3-DX controller (ARCOS) that speaks the real protocol over a pty or loopback TCP.

The emulator is the robot's side of the wire: it answers the SYNC0/1/2 handshake, streams a SIP every
100 ms after OPEN, obeys the motion commands through a kinematic robot model, and stops the robot when its
watchdog hears nothing for 2 s. Its SIPs report the model's ``odom_pose`` (the controller's own dead
reckoning, with the simulator's odometry error when the model has one).

Behaviour presets (:class:`EmulatorBehaviour`):
- ``real_robot=True`` (default): 15-bit positions, SIP type 0x33 while moving, motors disabled until ENABLE,
  sonar firing from OPEN as ARCOS does (SONAR 0 stops it), watchdog stop after 2 s of silence (motion
  resumes when packets return), partial sonar sets (a few new readings per SIP), ENCODER packets on request.

The CONFIG packet carries every field the reference client reads (:meth:`PioneerEmulator.config_packet`);
VEL and RVEL are capped at its current limits (TransVelMax, RotVelMax; SETV/SETRV change them up to the
Top values). The serial speed starts at 9600 baud; HOSTBAUD switches it and CLOSE returns it to 9600. Over a
pty the emulator compares its speed with the one the host set on its end (termios): while they differ the
bytes are lost both ways, as on a real line.
- ``real_robot=False``: the known simulator deviations: 0x32 always, 16-bit positions, motors and sonar
  enabled at start, no ENCODER packets, the watchdog only logs, all 16 sonar readings in every SIP.

Faults (:class:`EmulatorFaults`) act on the robot -> host byte stream: corrupted bytes, dropped bytes,
garbage between packets, a robot still open from an earlier session, and a link loss.

Times given to the emulator (SIP period, watchdog, fault times) are emulated seconds; ``time_scale`` > 1
runs them faster than real time (a SIP every 0.1 / time_scale real seconds).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import random
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from glassmap.sim.robot import DiffDriveRobot

from drivers.endpoints import PtyEndpoint
from drivers.pioneer.odometry import MODELS, PioneerModel, pose_to_units
from drivers.pioneer.packets import (SYNC0, SYNC1, SYNC2, Cmd, PacketParser, build_packet, parse_int_arg,
                                     vel2_split)
from drivers.pioneer.sip import (ConfigPacket, EncoderPacket, StandardSIP, SyncReply, encode_config,
                                 encode_encoder, encode_sip, encode_sync2)

log = logging.getLogger(__name__)


def default_robot(seed: int | None = 0) -> DiffDriveRobot:
    """The simulator's P3-DX kinematics with its default odometry error, seeded for repeatable runs."""
    return DiffDriveRobot(rng=np.random.default_rng(seed))


@dataclass(frozen=True)
class EmulatorBehaviour:
    """What the emulated controller does; :meth:`real` and :meth:`simulator` are the two presets."""

    position_bits: int = 15
    moving_type: bool = True  # SIP ID 0x33 while the robot moves
    motors_start_enabled: bool = False
    sonar_start_enabled: bool = True  # ARCOS fires the sonar from OPEN
    encoder_packets: bool = True
    watchdog_stops: bool = True
    sonar_per_sip: int | None = 4  # new sonar readings per SIP; None = all 16

    @classmethod
    def real(cls) -> EmulatorBehaviour:
        return cls()

    @classmethod
    def simulator(cls) -> EmulatorBehaviour:
        return cls(position_bits=16, moving_type=False, motors_start_enabled=True, sonar_start_enabled=True,
                   encoder_packets=False, watchdog_stops=False, sonar_per_sip=None)


@dataclass(frozen=True)
class EmulatorFaults:
    """Faults injected on the robot -> host stream (probabilities per outgoing packet).

    corrupt_rate: one byte of the packet XORed with a random non-zero value.
    drop_rate: 1-3 bytes of the packet removed.
    garbage_rate: 1-40 random bytes sent before the packet.
    still_open: the first host finds the robot open from an earlier session (streaming SIPs).
    link_loss_after: emulated seconds after OPEN at which the link drops once (None = never).
    link_outage: emulated seconds the link stays down (pty: then a new pty behind the same path).
    seed: random seed of the fault generator.
    """

    corrupt_rate: float = 0.0
    drop_rate: float = 0.0
    garbage_rate: float = 0.0
    still_open: bool = False
    link_loss_after: float | None = None
    link_outage: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("corrupt_rate", "drop_rate", "garbage_rate"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"EmulatorFaults.{name} must be a probability in [0, 1], got {p}")


@dataclass(frozen=True)
class ReceivedCommand:
    """A command the emulator received: emulated time (s), command number, integer argument or None."""

    t: float
    cmd: int
    arg: int | None


@dataclass
class EmulatorStats:
    sips_sent: int = 0
    packets_received: int = 0
    bad_packets_received: int = 0
    connections: int = 0
    link_losses: int = 0
    watchdog_trips: int = 0
    faults_injected: int = 0
    baud_mismatch_bytes: int = 0  # bytes lost because host and emulator ran at different serial speeds


_SESSION_CLOSED, _SESSION_SYNC1, _SESSION_SYNC2, _SESSION_READY, _SESSION_OPEN = range(5)

SONAR_COUNT = 16
SONAR_NO_ECHO_MM = 5000
SONAR_ARRAYS = 2  # array 0: front ring (sonar 0-7), array 1: rear ring (8-15)
HOSTBAUD_SPEEDS = (9600, 19200, 38400, 57600, 115200)  # HOSTBAUD code -> baud
POWER_UP_BAUD = 9600


class PioneerEmulator:
    """The controller of a Pioneer 3-DX (see module docstring).

    robot: a kinematic model with the interface of ``glassmap.sim.robot.DiffDriveRobot``
    (``set_velocity(v, omega)``, ``step(dt)``, ``odom_pose``, ``velocity``, ``wheel_speeds``); default
    :func:`default_robot` (a DiffDriveRobot with the simulator's odometry error, seeded with ``seed``). sonar_fn: optional ``f(index, odom_pose) -> metres``
    giving sonar ranges (default: no echo, 5 m).
    """

    def __init__(self, robot: Any = None, *, time_scale: float = 1.0, real_robot: bool = True,
                 faults: EmulatorFaults | None = None, behaviour: EmulatorBehaviour | None = None,
                 subclass: str = "p3dx-sh", name: str = "glassmap-emulator", sip_period: float = 0.1,
                 watchdog: float = 2.0, battery_volts: float = 12.6,
                 sonar_fn: Callable[[int, np.ndarray], float] | None = None, seed: int | None = 0) -> None:
        if time_scale <= 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        if subclass not in MODELS:
            raise ValueError(f"unknown subclass {subclass!r}; choose one of {sorted(MODELS)}")
        self.robot = robot if robot is not None else default_robot(seed)
        self.time_scale = float(time_scale)
        self.behaviour = behaviour or (EmulatorBehaviour.real() if real_robot else EmulatorBehaviour.simulator())
        self.faults = faults or EmulatorFaults()
        self.model: PioneerModel = MODELS[subclass]
        self.identity = SyncReply(name, "Pioneer", subclass)
        self.sip_period = sip_period
        self.watchdog = watchdog
        self.battery_volts = battery_volts
        self.sonar_fn = sonar_fn
        self.stats = EmulatorStats()
        self.received: list[ReceivedCommand] = []
        # Byte taps ``f(direction, monotonic time, data)``: "tx" host -> robot, "rx" robot -> host (a
        # drivers.capture.CaptureRecorder records a session from the robot's side).
        self.taps: list[Callable[[str, float, bytes], None]] = []
        self.stall_bumpers = 0  # raw STALL_BUMPERS bits to report (tests set this)
        self.hostbaud: int | None = None  # last HOSTBAUD code received
        self.line_baud = POWER_UP_BAUD  # the controller's serial speed (a pty host must match it)

        self._rng = random.Random(self.faults.seed)
        self._t0 = time.monotonic()
        self.cycle_monotonic: float | None = None  # time.monotonic() (s) of the cycle the robot was stepped to
        # held while a cycle steps the robot: a reader on another thread (the devices process's emulated
        # laser) takes it to see the robot and cycle_monotonic of one cycle
        self.lock = threading.Lock()
        self._virtual_t: float | None = None  # emulated time when offline (go_offline)
        self._session = _SESSION_OPEN if self.faults.still_open else _SESSION_CLOSED
        self._still_open_pending = self.faults.still_open
        self.motors_enabled = self.behaviour.motors_start_enabled
        self.sonar_enabled = self.behaviour.sonar_start_enabled
        self.sonar_arrays = (1 << SONAR_ARRAYS) - 1  # bit i: array i fires while the sonar is on
        self.estopped = False
        self._target = (0.0, 0.0)  # commanded (v m/s, omega rad/s)
        self._heading_goal: float | None = None  # rad, odom frame (HEAD/DHEAD mode)
        self._max_v = self.model.max_v
        self._max_omega = self.model.max_omega
        self._last_rx = self.now()
        self._watchdog_tripped = False
        self._encoder_mode = 0
        self._enc_mm = [0.0, 0.0]
        self._origin = np.zeros(3)  # SETO origin in the robot's odom frame
        self._sonar_next = 0
        self._open_since: float | None = None
        self._link_loss_done = False
        self._link_down_until: float | None = None

        self._writer: asyncio.StreamWriter | None = None
        self._conn_task: asyncio.Task | None = None
        self._tick_task: asyncio.Task | None = None
        self._attach_task: asyncio.Task | None = None  # re-attaching the pty after a link loss
        self._endpoint: PtyEndpoint | None = None
        self._pty_dir = ""
        self._server: asyncio.base_events.Server | None = None
        self._closed = False

    # -- public API ------------------------------------------------------------------------------------
    def now(self) -> float:
        """Emulated time (s) since the emulator was created (or since :meth:`go_offline`)."""
        if self._virtual_t is not None:
            return self._virtual_t
        return (time.monotonic() - self._t0) * self.time_scale

    # -- offline: the controller without a link or a clock, for deterministic replays -----------------
    def go_offline(self) -> None:
        """Run without a link and without real time: emulated time starts at 0 and moves only with
        :meth:`advance`; host bytes come in through :meth:`receive`; everything the controller sends goes
        to ``taps`` (stamped with emulated time)."""
        self._virtual_t = 0.0
        self._next_cycle = self.sip_period
        self._offline_parser = PacketParser(inter_byte_timeout=None)
        self._last_rx = 0.0

    def advance(self, t: float) -> None:
        """Offline: run the controller's cycles (one every ``sip_period``) up to emulated time ``t`` (s)."""
        if self._virtual_t is None:
            raise RuntimeError("advance() needs go_offline() first")
        while self._next_cycle <= t:
            self._virtual_t = self._next_cycle
            self._cycle(self._virtual_t, self.sip_period)
            self._next_cycle += self.sip_period
        self._virtual_t = max(self._virtual_t, t)

    def receive(self, data: bytes) -> None:
        """Offline: host -> controller bytes arriving at the current emulated time."""
        if self._virtual_t is None:
            raise RuntimeError("receive() needs go_offline() first")
        for tap in self.taps:
            tap("tx", self._virtual_t, data)
        for pkt in self._offline_parser.feed(data):
            self._handle(pkt.pid, pkt.payload)

    @property
    def is_open(self) -> bool:
        """True while a host session is open (SIPs streaming)."""
        return self._session == _SESSION_OPEN

    @property
    def commanded_velocity(self) -> tuple[float, float]:
        """Current setpoint (v m/s, omega rad/s) as commanded by the host (before watchdog/motor state)."""
        return self._target

    async def serve_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns the host's URL ``serial://PATH?baud=9600``."""
        self._pty_dir = tempfile.mkdtemp(prefix="glassmap-pioneer-")
        self._endpoint = PtyEndpoint(self._pty_dir, name="pioneer", baud=POWER_UP_BAUD)
        await self._attach_pty()
        self._start_ticking()
        return f"serial://{self._endpoint.path}?baud=9600"

    async def serve_tcp(self, port: int = 0, host: str = "127.0.0.1") -> str:
        """Serve on loopback TCP (port 0 picks a free one); returns ``tcp://127.0.0.1:PORT``."""
        self._server = await asyncio.start_server(self._on_tcp, host, port)
        self._start_ticking()
        return f"tcp://{host}:{self._server.sockets[0].getsockname()[1]}"

    def link_loss(self, outage: float | None = None) -> None:
        """Drop the link now; it comes back after ``outage`` emulated seconds (default faults.link_outage).

        The controller stays as it was (a serial cable pulled: still open, its watchdog will stop it); over
        TCP the connection is closed and new connections are refused during the outage.
        """
        outage = self.faults.link_outage if outage is None else outage
        self.stats.link_losses += 1
        self._link_down_until = self.now() + outage
        log.info("emulator: link loss for %.2f s", outage)
        self._drop_connection()
        if self._endpoint is not None:
            self._endpoint.hangup()
            asyncio.get_running_loop().call_later(outage / self.time_scale, self._restore_pty)

    async def close(self) -> None:
        """Stop serving (the host sees the link drop)."""
        self._closed = True
        for task in (self._tick_task, self._conn_task, self._attach_task):
            if task is not None:
                task.cancel()
        self._drop_connection()
        if self._server is not None:
            self._server.close()
        if self._endpoint is not None:
            self._endpoint.close()
            with contextlib.suppress(OSError):
                os.rmdir(self._pty_dir)
        await asyncio.sleep(0)

    async def __aenter__(self) -> PioneerEmulator:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- links -----------------------------------------------------------------------------------------
    async def _attach_pty(self) -> None:
        if self._endpoint is None:
            raise RuntimeError("the emulator has no pty to attach (serve_pty() was not called)")
        reader, writer = await self._endpoint.open()
        self._start_connection(reader, writer)

    def _restore_pty(self) -> None:
        if self._closed or self._endpoint is None:
            return
        self._endpoint.reopen()
        self._link_down_until = None
        self._attach_task = asyncio.ensure_future(self._attach_pty())

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._link_down_until is not None and self.now() < self._link_down_until:
            writer.close()
            return
        self._link_down_until = None
        # A TCP simulator starts each connection with a fresh session unless a stale one is injected.
        if self._still_open_pending:
            self._still_open_pending = False
        else:
            self._close_session()
        self._start_connection(reader, writer)
        if self._conn_task is not None:
            try:
                await self._conn_task
            except asyncio.CancelledError:
                pass

    def _start_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._drop_connection()
        self.stats.connections += 1
        self._writer = writer
        self._conn_task = asyncio.ensure_future(self._serve_connection(reader, writer))

    def _drop_connection(self) -> None:
        if self._conn_task is not None and not self._conn_task.done():
            self._conn_task.cancel()
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:  # already closed by the peer
                pass
        self._writer = None

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        parser = PacketParser(inter_byte_timeout=None)
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    break
                for tap in self.taps:
                    tap("tx", time.monotonic(), data)
                if not self._speeds_match():
                    self.stats.baud_mismatch_bytes += len(data)
                    continue
                for pkt in parser.feed(data):
                    self._handle(pkt.pid, pkt.payload)
                self.stats.bad_packets_received = parser.stats.bad_checksum + parser.stats.bad_length
        except (ConnectionError, OSError):
            pass
        finally:
            if self._writer is writer:
                self._writer = None
            try:
                writer.close()  # the peer hung up: release our end too
            except Exception:  # already closed (link loss)
                pass

    def _speeds_match(self) -> bool:
        """False when a pty host runs its end at another serial speed than the controller."""
        host = self._endpoint.host_baud() if self._endpoint is not None else None
        return host is None or host == self.line_baud

    def _write(self, data: bytes) -> None:
        if self._virtual_t is not None:
            for tap in self.taps:
                tap("rx", self._virtual_t, data)
            return
        w = self._writer
        if w is None or w.is_closing():
            return
        if not self._speeds_match():
            self.stats.baud_mismatch_bytes += len(data)
            return
        if w.transport.get_write_buffer_size() > 1 << 16:  # nobody reading: bytes are lost, as on a wire
            return
        try:
            w.write(data)
        except (ConnectionError, OSError, RuntimeError):
            self._writer = None
            return
        for tap in self.taps:
            tap("rx", time.monotonic(), data)

    def _send(self, packet: bytes) -> None:
        f = self.faults
        data = bytearray(packet)
        rng = self._rng
        if f.garbage_rate and rng.random() < f.garbage_rate:
            data[0:0] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))
            self.stats.faults_injected += 1
        if f.corrupt_rate and rng.random() < f.corrupt_rate:
            k = rng.randrange(len(data))
            data[k] ^= rng.randint(1, 255)
            self.stats.faults_injected += 1
        if f.drop_rate and rng.random() < f.drop_rate:
            for _ in range(min(rng.randint(1, 3), len(data) - 1)):
                del data[rng.randrange(len(data))]
            self.stats.faults_injected += 1
        self._write(bytes(data))

    # -- protocol --------------------------------------------------------------------------------------
    def _handle(self, pid: int, payload: bytes) -> None:
        self.stats.packets_received += 1
        self._last_rx = self.now()
        if self._watchdog_tripped:
            self._watchdog_tripped = False
            log.info("emulator: packets again, watchdog released")
        if self._session != _SESSION_OPEN:
            self._handshake(pid)
            return
        arg = parse_int_arg(payload)
        self.received.append(ReceivedCommand(self.now(), pid, arg))
        self._command(pid, arg)

    def _handshake(self, pid: int) -> None:
        s = self._session
        if pid == SYNC0:
            self._session = _SESSION_SYNC1
            self._send(build_packet(SYNC0))
        elif pid == SYNC1 and s == _SESSION_SYNC1:
            self._session = _SESSION_SYNC2
            self._send(build_packet(SYNC1))
        elif pid == SYNC2 and s == _SESSION_SYNC2:
            self._session = _SESSION_READY
            self._send(encode_sync2(self.identity))
        elif pid == Cmd.OPEN and s == _SESSION_READY:
            self._open_session()
        elif pid == Cmd.CLOSE:
            self._session = _SESSION_CLOSED
            self.line_baud = POWER_UP_BAUD
        # anything else before OPEN is ignored, as ARCOS does

    def _open_session(self) -> None:
        self._session = _SESSION_OPEN
        self._open_since = self.now()
        self.motors_enabled = self.behaviour.motors_start_enabled
        self.sonar_enabled = self.behaviour.sonar_start_enabled
        self.sonar_arrays = (1 << SONAR_ARRAYS) - 1
        cfg = self.config_packet()
        self._max_v = min(cfg.transvel_max / 1000.0, self.model.max_v)
        self._max_omega = min(math.radians(cfg.rotvel_max), self.model.max_omega)
        self._target = (0.0, 0.0)
        self._heading_goal = None
        self._encoder_mode = 0
        self.received.append(ReceivedCommand(self.now(), int(Cmd.OPEN), None))

    def _close_session(self) -> None:
        self._session = _SESSION_CLOSED
        self._target = (0.0, 0.0)
        self._heading_goal = None
        if not self.behaviour.motors_start_enabled:
            self.motors_enabled = False

    def _command(self, cmd: int, arg: int | None) -> None:
        m = self.model
        if cmd == Cmd.CLOSE:
            self._close_session()
            self.line_baud = POWER_UP_BAUD
        elif cmd == Cmd.ENABLE:
            self.motors_enabled = bool(arg)
            if not self.motors_enabled:
                self._target = (0.0, 0.0)
        elif cmd == Cmd.VEL and arg is not None:
            v = float(np.clip(arg / 1000.0, -self._max_v, self._max_v))
            self._target = (v, self._target[1])
            self.estopped = False
        elif cmd == Cmd.RVEL and arg is not None:
            w = float(np.clip(math.radians(arg), -self._max_omega, self._max_omega))
            self._target = (self._target[0], w)
            self._heading_goal = None
            self.estopped = False
        elif cmd == Cmd.VEL2 and arg is not None:
            left, right = (u * m.vel2_divisor for u in vel2_split(arg))
            self._target = ((left + right) / 2000.0, (right - left) / 2.0 * m.diff_conv)
            self._heading_goal = None
            self.estopped = False
        elif cmd in (Cmd.HEAD, Cmd.DHEAD) and arg is not None:
            base = 0.0 if cmd == Cmd.HEAD else self._reported_pose()[2]
            self._heading_goal = base + math.radians(arg)
            self.estopped = False
        elif cmd == Cmd.STOP:
            self._target = (0.0, 0.0)
            self._heading_goal = None
        elif cmd == Cmd.ESTOP:
            self._target = (0.0, 0.0)
            self._heading_goal = None
            self.estopped = True
            halt = getattr(self.robot, "halt", None)  # a model that can stop at once; else its max decel
            if halt is not None:
                halt()
            self.robot.set_velocity(0.0, 0.0)
        elif cmd == Cmd.SETV and arg is not None:
            self._max_v = min(abs(arg) / 1000.0, m.max_v)
        elif cmd == Cmd.SETRV and arg is not None:
            self._max_omega = min(math.radians(abs(arg)), m.max_omega)
        elif cmd == Cmd.SETO:
            self._origin = np.asarray(self.robot.odom_pose, dtype=float).copy()
        elif cmd == Cmd.CONFIG:
            self._send(encode_config(self.config_packet()))
        elif cmd == Cmd.ENCODER and arg is not None and self.behaviour.encoder_packets:
            self._encoder_mode = arg
        elif cmd == Cmd.SONAR and arg is not None:
            # ARCOS: bit 0 on/off; bits 1-4 pick arrays (none = all arrays).
            every = (1 << SONAR_ARRAYS) - 1
            mask = (arg >> 1) & every or every
            if arg & 1:
                self.sonar_arrays = mask if not self.sonar_enabled else self.sonar_arrays | mask
            else:
                self.sonar_arrays &= ~mask
            self.sonar_enabled = self.sonar_arrays != 0
            if not self.sonar_enabled:
                self.sonar_arrays = every
        elif cmd == Cmd.HOSTBAUD and arg is not None:
            self.hostbaud = arg
            if 0 <= arg < len(HOSTBAUD_SPEEDS) and self.config_packet().reset_baud == 2:
                self.line_baud = HOSTBAUD_SPEEDS[arg]
        # PULSE, OPEN, SETA, SETRA and unknown commands: nothing to do (acceleration is the model's)

    def config_packet(self) -> ConfigPacket:
        """The CONFIG packet: every field ARIA reads, with P3-DX values (ARCOS units: mm, deg, ms, 0.1 V)."""
        return ConfigPacket(
            "Pioneer", self.identity.subclass, "EMU0001", four_mots=0, rotvel_top=500, transvel_top=2200,
            rotaccel_top=300, transaccel_top=2000, pwm_max=1000, name=self.identity.name,
            sip_cycle=int(round(self.sip_period * 1000)), host_baud=0, aux_baud=0, gripper=0, front_sonar=1,
            rear_sonar=1, low_battery=110, revcount=16570, watchdog=int(round(self.watchdog * 1000)),
            normal_mpacs=0, stall_val=255, stall_count=10, joy_vel=300, joy_rotvel=50, rotvel_max=300,
            transvel_max=1500, rot_accel=200, rot_decel=200, rot_kp=40, rot_kv=20, rot_ki=0, trans_accel=300,
            trans_decel=300, trans_kp=40, trans_kv=30, trans_ki=0, front_bumps=5, rear_bumps=5, has_charger=0,
            sonar_cycle=40, reset_baud=2, gyro_type=0, drift_factor=0, aux2_baud=0, aux3_baud=0, ticks_mm=128,
            shutdown_voltage=105, firmware_version="glassmap emulated ARCOS", gyro_cw=0, gyro_ccw=0,
            kinematics_delay=0, latvel_top=0, lataccel_top=0, latvel_max=0, lat_accel=0, lat_decel=0,
            charge_threshold=0, pdb_port=0, gyro_rate_limit=0, high_temperature_shutdown=0, power_bits=0,
            battery_type=0, state_of_charge_low=0, state_of_charge_shutdown=0, bootloader_version="",
            config_flags=0, gyro_fw_version=0)

    # -- the controller's cycle ------------------------------------------------------------------------
    def _start_ticking(self) -> None:
        if self._tick_task is None:
            self._tick_task = asyncio.ensure_future(self._tick_loop())

    async def _tick_loop(self) -> None:
        # A controller's cycle: SIP n reports the robot at n * sip_period however late this loop runs it, and
        # a loop that fell far behind (a loaded machine) skips whole cycles rather than bursting or drifting.
        period = self.sip_period / self.time_scale
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            skipped = max(int((time.monotonic() - next_t) / period) - 4, 0)  # > 5 periods behind: skip
            next_t += skipped * period
            now = self.now()
            dt = (1 + skipped) * self.sip_period
            try:
                with self.lock:
                    self.cycle_monotonic = next_t
                    self._cycle(now, dt)
            except Exception:  # keep the controller alive; a bug here must show in the log
                log.exception("emulator cycle failed")

    def _cycle(self, now: float, dt: float) -> None:
        b = self.behaviour
        if self.is_open and now - self._last_rx > self.watchdog:
            if not self._watchdog_tripped:
                self._watchdog_tripped = True
                self.stats.watchdog_trips += 1
                log.info("emulator: watchdog: no packets for %.1f s%s", self.watchdog,
                         ", stopping" if b.watchdog_stops else " (simulator: only logging)")
        stopped = (not self.motors_enabled or self.estopped or not self.is_open
                   or (self._watchdog_tripped and b.watchdog_stops))
        v, w = (0.0, 0.0) if stopped else self._target
        if not stopped and self._heading_goal is not None:
            err = math.atan2(math.sin(self._heading_goal - self._reported_pose()[2]),
                             math.cos(self._heading_goal - self._reported_pose()[2]))
            w = float(np.clip(3.0 * err, -min(self._max_omega, math.radians(100)),
                              min(self._max_omega, math.radians(100))))
        self.robot.set_velocity(v, w)
        self.robot.step(dt)
        wl, wr = self.robot.wheel_speeds
        self._enc_mm[0] += wl * 1000.0 * dt
        self._enc_mm[1] += wr * 1000.0 * dt
        if (self._open_since is not None and self.faults.link_loss_after is not None and not self._link_loss_done
                and self.is_open and now - self._open_since >= self.faults.link_loss_after):
            self._link_loss_done = True
            self.link_loss()
        if self.is_open:
            self._send(encode_sip(self._sip()))
            self.stats.sips_sent += 1
            if self._encoder_mode:
                ticks_per_mm = 128.0
                self._send(encode_encoder(EncoderPacket(int(self._enc_mm[0] * ticks_per_mm) & 0x7FFFFFFF,
                                                        int(self._enc_mm[1] * ticks_per_mm) & 0x7FFFFFFF)))
                if self._encoder_mode == 1:
                    self._encoder_mode = 0

    def _reported_pose(self) -> np.ndarray:
        """The controller's odometry relative to the last SETO (odom frame, m and rad)."""
        p = np.asarray(self.robot.odom_pose, dtype=float)
        o = self._origin
        c, s = math.cos(o[2]), math.sin(o[2])
        dx, dy = p[0] - o[0], p[1] - o[1]
        return np.array([c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(p[2] - o[2]),
                                                                       math.cos(p[2] - o[2]))])

    def _sip(self) -> StandardSIP:
        m, b = self.model, self.behaviour
        x, y, th = self._reported_pose()
        xu, yu, thu = pose_to_units(x, y, th, m, b.position_bits)
        wl, wr = self.robot.wheel_speeds
        v, w = self.robot.velocity
        moving = abs(v) > 1e-3 or abs(w) > 1e-3
        flags = (1 if self.motors_enabled else 0) | ((self.sonar_arrays << 1) if self.sonar_enabled else 0) | (
            0x20 if self.estopped else 0)
        goal = th if self._heading_goal is None else self._heading_goal
        control = int(round(goal / m.angle_conv)) % 4096
        control = control - 4096 if control >= 2048 else control
        batt = int(round(self.battery_volts * 10))
        return StandardSIP(moving=bool(moving and b.moving_type), xpos=xu, ypos=yu, thpos=thu,
                           lvel=int(round(wl * 1000.0 / m.vel_conv)), rvel=int(round(wr * 1000.0 / m.vel_conv)),
                           battery=min(batt, 255), stall_bumpers=self.stall_bumpers & 0xFFFF, control=control,
                           flags=flags, compass=0, sonar=self._sonar_readings(), grip=0, anport=0, analog=0,
                           digin=0, digout=0, battery_x10=batt, charge_state=0,
                           rotvel=int(round(math.degrees(w) * 10)), fault_flags=0)

    def _sonar_readings(self) -> tuple[tuple[int, int], ...]:
        if not self.sonar_enabled:
            return ()
        per_array = SONAR_COUNT // SONAR_ARRAYS
        firing = [i for i in range(SONAR_COUNT) if self.sonar_arrays >> (i // per_array) & 1]
        n = min(self.behaviour.sonar_per_sip or SONAR_COUNT, len(firing))
        start = next((k for k, i in enumerate(firing) if i >= self._sonar_next), 0)
        idx = [firing[(start + k) % len(firing)] for k in range(n)]
        self._sonar_next = (idx[-1] + 1) % SONAR_COUNT if idx else 0
        pose = self._reported_pose()
        out = []
        for i in idx:
            rng_m = self.sonar_fn(i, pose) if self.sonar_fn is not None else SONAR_NO_ECHO_MM / 1000.0
            out.append((i, int(np.clip(round(rng_m * 1000.0), 0, 0xFFFF))))
        return tuple(out)
