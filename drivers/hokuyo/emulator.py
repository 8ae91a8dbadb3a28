"""An emulated Hokuyo UTM-30LX-EW: speaks SCIP 2.0 over loopback TCP or a pseudo-terminal.

The sensor's side of the wire, for tests, demos and interop checks. It keeps the real unit's state
machine (idle, laser on, streaming, time-sync mode, rebooting), its 24-bit millisecond clock, 40 Hz scans
(one revolution every 60 / SCAN s) stamped at their first step and sent right after the sweep, one reply
per write, LF-only output; it accepts LF, CR or CR+LF after host commands. ``time_scale`` > 1 runs the
emulated time (clock, scan rate) that many times faster than real time.

Scans come from ``scan_source(t) -> (ranges_m, intensities)`` with ``t`` emulated seconds since start;
arrays of shape (1081,) or (1081, e) for several echoes (NaN / inf where an extra echo is absent).
Ranges follow REP 117 (NaN invalid -> error code 3, +inf no return -> code 1, below DMIN -> code 2).

Faults (:class:`Faults`) are applied to the stream at chosen scan numbers, and :attr:`HokuyoEmulator.stats`
says what was done, so tests can check that a client kept every good scan and counted every bad one.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers.endpoints import PtyEndpoint, serve_pty, serve_tcp
from drivers.hokuyo.scip import (
    MAX_STRING,
    SINGLE_COMMANDS,
    STREAM_COMMANDS,
    TIMESTAMP_MOD,
    encode_reply,
    encode_scan_payload,
    encode_values,
    expected_steps,
    value_width,
    info_line,
)

log = logging.getLogger(__name__)

ScanSource = Callable[[float], tuple[np.ndarray, np.ndarray]]

UTM_30LX_EW_PARAMS: dict[str, int | str] = {
    "MODL": "UTM-30LX-EW", "DMIN": 23, "DMAX": 60000, "ARES": 1440, "AMIN": 0, "AMAX": 1080,
    "AFRT": 540, "SCAN": 2400,
}
UTM_30LX_EW_VERSION: dict[str, str] = {
    "VEND": "Hokuyo Automatic Co.,Ltd.", "PROD": "SOKUIKI Sensor TOP-URG UTM-30LX-EW",
    "FIRM": "1.1.3(19/Jun./2012)", "PROT": "SCIP 2.0", "SERI": "H1311476",
}
_UNSUPPORTED = {"RT": "0F", "SS": "0F", "CR": "0F", "HS": "0F", "%ST": "0E", "%SL": "0E"}
_STATUS_FAULTS = ("0L", "0M", "0E")


@dataclass
class Faults:
    """Faults injected into the scan stream. ``*_every = n`` hits scans n, 2n, 3n, ... (0 = never);
    ``*_at = k`` happens once, at scan k (counted over the emulator's lifetime, from 0).

    At most one per-scan fault hits a scan, in this order: status, checksum, drop, garbage, coalesce.
    - status_every: the scan is replaced by a stream message with status 0L, 0M, 0E (cycled).
    - checksum_every: one data line of the scan gets a wrong checksum character.
    - drop_every: one payload byte of a data line of the scan is dropped.
    - garbage_every: 1-40 random bytes (LF included) are written between messages before the scan.
    - coalesce_every: the scan is held back and written together with the next one in one write.
    - clock_jump_at: the sensor clock jumps by clock_jump_s before scan k is stamped.
    - disconnect_at: the link drops before scan k (cable pulled and plugged back in).
    - reboot_at: the sensor reboots before scan k (link drops, clock restarts at 0, boot_time offline).
    - silence_at: the sensor hangs for silence_s (emulated s): no scans, no replies.
    - ignore_qt: the first n QT commands are ignored (no reply, the stream goes on).
    """

    seed: int = 0
    status_every: int = 0
    checksum_every: int = 0
    drop_every: int = 0
    garbage_every: int = 0
    coalesce_every: int = 0
    clock_jump_at: int | None = None
    clock_jump_s: float = 60.0
    disconnect_at: int | None = None
    reboot_at: int | None = None
    silence_at: int | None = None
    silence_s: float = 2.0
    ignore_qt: int = 0

    @classmethod
    def parse(cls, spec: str) -> Faults:
        """From ``"checksum_every=50,drop_every=70,reboot_at=200"`` (the CLI form). ValueError if bad."""
        kw: dict[str, float | int] = {}
        names = {f for f in cls.__dataclass_fields__}
        for part in filter(None, (p.strip() for p in spec.split(","))):
            key, _, val = part.partition("=")
            if key not in names or not val:
                raise ValueError(f"bad fault {part!r}: use NAME=VALUE with NAME in {sorted(names)}")
            try:
                kw[key] = float(val) if key in ("clock_jump_s", "silence_s") else int(val)
            except ValueError:
                raise ValueError(f"bad fault {part!r}: {key} takes a number") from None
        return cls(**kw)


@dataclass
class EmulatorStats:
    """What the emulator sent and did. ``good_stamps``: raw 24-bit stamps of the intact scans sent;
    ``overruns``: scans not made because this machine fell behind, or not sent because the host did not read."""

    scans_good: int = 0
    scans_corrupted: int = 0
    error_statuses: int = 0
    garbage_writes: int = 0
    garbage_bytes: int = 0
    coalesced: int = 0
    clock_jumps: int = 0
    disconnects: int = 0
    reboots: int = 0
    silences: int = 0
    qt_ignored: int = 0
    overruns: int = 0
    connections: int = 0
    commands: int = 0
    good_stamps: deque = field(default_factory=lambda: deque(maxlen=100_000))


# ------------------------------------------------------------------------------------------ scan sources
def ranges_to_codes(ranges_m: np.ndarray, dmin: int = 23, dmax: int = 60000) -> np.ndarray:
    """Metres -> SCIP millimetres with error codes: NaN -> 3, +inf or > dmax -> 1, < dmin -> 2."""
    r = np.asarray(ranges_m, np.float64)
    with np.errstate(invalid="ignore"):
        mm = np.rint(np.where(np.isfinite(r), r, 0.0) * 1000.0)
        out = np.where(np.isnan(r), 3, np.where(np.isinf(r) | (mm > dmax), 1, np.where(mm < dmin, 2, mm)))
    return out.astype(np.int64)


def room_scan_source(width: float = 8.0, depth: float = 5.0, spin: float = 0.2, n_beams: int = 1081,
                     angle_min: float = -3 * math.pi / 4, angle_increment: float = math.pi / 720) -> ScanSource:
    """A laser at the centre of a ``width`` x ``depth`` m rectangular room, turning at ``spin`` rad/s.

    Deterministic; intensities fall with range and incidence angle. Good for demos without the simulator.
    """
    ang = angle_min + angle_increment * np.arange(n_beams)
    hx, hy = width / 2, depth / 2

    def source(t: float) -> tuple[np.ndarray, np.ndarray]:
        th = ang + spin * t
        c, s = np.cos(th), np.sin(th)
        with np.errstate(divide="ignore"):
            tx = np.where(np.abs(c) > 1e-12, hx / np.abs(c), np.inf)
            ty = np.where(np.abs(s) > 1e-12, hy / np.abs(s), np.inf)
        r = np.minimum(tx, ty)
        cos_inc = np.where(tx < ty, np.abs(c), np.abs(s))
        inten = 6000.0 * cos_inc / np.maximum(r, 0.1) + 200.0
        return r, inten

    return source


def canned_scan_source(ranges: np.ndarray, intensities: np.ndarray, period: float = 0.025) -> ScanSource:
    """Replays recorded scans (arrays (k, n) or (k, n, e)) in a loop, scan floor(t / period) mod k."""
    R, I = np.asarray(ranges, np.float64), np.asarray(intensities, np.float64)
    if R.ndim == 1:
        R, I = R[None], I[None]
    if R.shape != I.shape:
        raise ValueError(f"canned scans: ranges {R.shape} and intensities {I.shape} differ")

    def source(t: float) -> tuple[np.ndarray, np.ndarray]:
        k = int(math.floor(t / period + 1e-9)) % R.shape[0]
        return R[k], I[k]

    return source


def sim_scan_source(world, laser_pose_fn: Callable[[float], np.ndarray], seed: int = 0, params=None,
                    on_scan: Callable | None = None) -> ScanSource:
    """Scans of a simulated world (``glassmap.sim``): ``laser_pose_fn(t)`` gives the laser pose (x, y, yaw)
    in the map frame at emulated time t. ``world`` is a World or a built-in name / path. When the simulator
    gives first and last echoes, both are served (multi-echo commands see them). ``on_scan(pose, sim)``, if
    given, sees every simulated scan (e.g. to record which cells were seen)."""
    from glassmap.sim.laser import simulate_scan, world_laser_params
    from glassmap.sim.world import load_world

    w = load_world(world) if isinstance(world, str) else world
    rng = np.random.default_rng(seed)
    p = params or world_laser_params(w)

    def source(t: float) -> tuple[np.ndarray, np.ndarray]:
        pose = np.asarray(laser_pose_fn(t), np.float64)
        s = simulate_scan(w, pose, rng, p)
        if on_scan is not None:
            on_scan(pose, s)
        if s.echo_ranges is None:
            return s.ranges, s.intensities
        return (np.column_stack([s.ranges, s.echo_ranges[:, 1]]),
                np.column_stack([s.intensities, s.echo_intensities[:, 1]]))

    return source


# ------------------------------------------------------------------------------------------- emulator
@dataclass
class _Conn:
    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    kind: str
    closed: bool = False
    stream: asyncio.Task | None = None
    pending: bytes = b""


class HokuyoEmulator:
    """A UTM-30LX-EW on the other side of a pty or a loopback socket (one host connection at a time)."""

    def __init__(self, scan_source: ScanSource | None = None, *, time_scale: float = 1.0,
                 faults: Faults | None = None, clock_start_ms: int = 0, boot_time: float = 2.0,
                 tm_refusal_after_boot: float = 3.0, params: dict | None = None) -> None:
        if time_scale <= 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.scan_source = scan_source or room_scan_source()
        self.time_scale = float(time_scale)
        self.faults = faults or Faults()
        self.params = dict(UTM_30LX_EW_PARAMS, **(params or {}))
        self.boot_time = boot_time
        self.tm_refusal_after_boot = tm_refusal_after_boot
        self.stats = EmulatorStats()
        self.state = "idle"  # idle | laser_on | streaming | time_sync | booting
        self.url: str | None = None
        self._rng = np.random.default_rng(self.faults.seed)
        self._real0: float | None = None
        self._clock_epoch = 0.0
        self._clock_offset_ms = int(clock_start_ms)
        self._conn: _Conn | None = None
        self._server: asyncio.base_events.Server | None = None
        self._pty: PtyEndpoint | None = None
        self._tasks: set[asyncio.Task] = set()
        self._scan_no = 0
        self._silent_until = -1.0
        self._booting_until = -1.0
        self._tm_refuse_until = -1.0
        self._last_rb = -math.inf
        self._qt_to_ignore = self.faults.ignore_qt
        # Byte taps ``f(direction, monotonic time, data)``: "tx" host -> sensor, "rx" sensor -> host (a
        # drivers.capture.CaptureRecorder records a session from the sensor's side).
        self.taps: list[Callable[[str, float, bytes], None]] = []

    # -- time ---------------------------------------------------------------------------------------
    def loop_time(self, t: float) -> float | None:
        """Event-loop time (s; time.monotonic() on the default loop) of emulated time ``t``; None before
        the emulator has served."""
        return None if self._real0 is None else self._real0 + t / self.time_scale

    def now(self) -> float:
        """Emulated seconds since the emulator started serving."""
        loop = asyncio.get_running_loop()
        if self._real0 is None:
            self._real0 = loop.time()
        return (loop.time() - self._real0) * self.time_scale

    def clock_ms(self, t: float | None = None) -> int:
        """The sensor's 24-bit millisecond clock at emulated time t (default now)."""
        t = self.now() if t is None else t
        return (int(math.floor((t - self._clock_epoch) * 1000.0)) + self._clock_offset_ms) % TIMESTAMP_MOD

    async def _sleep_until(self, t: float) -> None:
        delay = (t - self.now()) / self.time_scale
        if delay > 0:
            await asyncio.sleep(delay)

    @property
    def scan_period(self) -> float:
        """One revolution (emulated s): 60 / SCAN rpm."""
        return 60.0 / float(self.params["SCAN"])

    # -- serving ------------------------------------------------------------------------------------
    async def serve_tcp(self, port: int = 0, host: str = "127.0.0.1") -> str:
        """Listen on loopback TCP; returns ``tcp://host:port``."""
        self.now()
        self._server = await serve_tcp(self._on_tcp, host, port)
        port = self._server.sockets[0].getsockname()[1]
        self.url = f"tcp://{host}:{port}"
        return self.url

    async def serve_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns ``serial:///path/to/link``."""
        self.now()
        self._pty = PtyEndpoint(name="hokuyo")
        self._spawn(serve_pty(self._on_pty, self._pty))
        self.url = f"serial://{self._pty.path}"
        return self.url

    async def close(self) -> None:
        """Stop serving and drop the connection."""
        if self._server is not None:
            self._server.close()
        if self._conn is not None:
            self._drop(self._conn)
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._pty is not None:
            self._pty.close()
        if self._server is not None:
            try:
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
            except asyncio.TimeoutError:
                pass

    async def __aenter__(self) -> HokuyoEmulator:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    def _spawn(self, coro) -> asyncio.Task:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.now() < self._booting_until:
            writer.close()  # still booting: the link comes up and drops at once
            return
        await self._serve(_Conn(reader, writer, "tcp"))

    async def _on_pty(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await self._serve(_Conn(reader, writer, "pty"))

    async def _serve(self, conn: _Conn) -> None:
        if self._conn is not None:
            self._drop(self._conn)
        self._conn = conn
        self.stats.connections += 1
        self._stop_stream()
        buf = bytearray()
        try:
            while not conn.closed:
                data = await conn.reader.read(4096)
                if not data:
                    break
                for tap in self.taps:
                    tap("tx", time.monotonic(), data)
                buf += data
                *lines, rest = re.split(rb"\r\n|\r|\n", bytes(buf))
                buf = bytearray(rest[-256:])
                for line in lines:
                    if line and not conn.closed:
                        await self._command(conn, line)
        except (ConnectionError, OSError):
            pass
        finally:
            if self._conn is conn:
                self._drop(conn)

    def _drop(self, conn: _Conn) -> None:
        """Close one connection (its stream stops with it)."""
        if conn.closed:
            return
        conn.closed = True
        if conn.stream is not None:
            conn.stream.cancel()
        try:
            conn.writer.close()
        except (OSError, RuntimeError):
            pass
        rt = getattr(conn.reader, "_transport", None)  # the pty read pipe holds a dup of the master
        if conn.kind == "pty" and rt is not None:
            rt.close()
        if self._conn is conn:
            self._conn = None
            if self.state in ("streaming", "time_sync"):
                self.state = "laser_on" if self.state == "streaming" else "idle"

    def _write(self, conn: _Conn, data: bytes) -> bool:
        """One write of whole replies (plus any held-back coalesced reply). False if not sent."""
        if conn.closed:
            return False
        transport = conn.writer.transport
        if transport.get_write_buffer_size() > (1 << 20):
            self.stats.overruns += 1  # host not reading: drop, as the sensor would
            return False
        conn.writer.write(conn.pending + data)
        for tap in self.taps:
            tap("rx", time.monotonic(), conn.pending + data)
        conn.pending = b""
        return True

    # -- link events ----------------------------------------------------------------------------------
    async def disconnect(self, *, settle: float = 0.25) -> None:
        """Cable pull: drop the link (a pty re-appears at once behind the same path)."""
        conn = self._conn
        if conn is None:
            return
        self._write(conn, b"")  # a held-back (coalesced) reply still goes out
        await asyncio.sleep(settle)  # let the host read what is already on the wire
        log.info("emulator: link dropped (cable pull)")
        self.stats.disconnects += 1
        self._drop(conn)
        if conn.kind == "pty" and self._pty is not None:
            self._pty.reopen()
            self._spawn(serve_pty(self._on_pty, self._pty))

    async def reboot(self, *, settle: float = 0.25) -> None:
        """Reboot: drop the link, offline for ``boot_time`` (emulated s), clock restarts at 0, laser off."""
        conn = self._conn
        log.info("emulator: rebooting (%.1f s emulated)", self.boot_time)
        self.stats.reboots += 1
        self.state = "booting"  # from here on no command is answered
        self._booting_until = math.inf
        if conn is not None:
            self._write(conn, b"")  # a held-back (coalesced) reply still goes out
            await asyncio.sleep(settle)  # let the host read what is already on the wire
            self._drop(conn)
        self._booting_until = self.now() + self.boot_time
        if self._pty is not None:
            self._pty.hangup()
        await self._sleep_until(self._booting_until)
        self._clock_epoch, self._clock_offset_ms = self.now(), 0
        self._tm_refuse_until = self.now() + self.tm_refusal_after_boot
        self.state = "idle"
        if self._pty is not None:
            self._pty.reopen()
            self._spawn(serve_pty(self._on_pty, self._pty))

    def jump_clock(self, seconds: float) -> None:
        """Move the sensor clock by ``seconds`` (a clock fault)."""
        self.stats.clock_jumps += 1
        self._clock_offset_ms += int(round(seconds * 1000.0))

    def silence(self, seconds: float) -> None:
        """Hang for ``seconds`` emulated: no scans and no replies."""
        self.stats.silences += 1
        self._silent_until = self.now() + seconds

    # -- commands ------------------------------------------------------------------------------------
    def _stop_stream(self) -> None:
        conn = self._conn
        if conn is not None and conn.stream is not None:
            conn.stream.cancel()
            conn.stream = None
        if self.state == "streaming":
            self.state = "laser_on"

    def _reply(self, conn: _Conn, echo: bytes, status: str, payload: bytes = b"") -> None:
        self._write(conn, encode_reply(echo, status, payload))

    async def _command(self, conn: _Conn, line: bytes) -> None:
        if self.now() < self._silent_until or self.state == "booting":
            return
        self.stats.commands += 1
        await asyncio.sleep(0.0005 / self.time_scale)  # the sensor's processing time
        head, _, string = line.partition(b";")
        cmd = head[:3] if head.startswith(b"%") else head[:2]
        params = head[len(cmd):]
        name = cmd.decode("ascii", "replace")
        if len(string) > MAX_STRING:
            return self._reply(conn, line, "0G")
        if name in ("VV", "PP", "II"):
            fields = {"VV": self._version, "PP": self._pp, "II": self._ii}[name]()
            payload = b"".join(info_line(k, str(v)) for k, v in fields.items())
            return self._reply(conn, line, "00", payload)
        if name == "BM":
            if self.state == "time_sync":
                return self._reply(conn, line, "10")
            status = "00" if self.state == "idle" else "02"
            if self.state == "idle":
                self.state = "laser_on"
            return self._reply(conn, line, status)
        if name == "QT":
            if self._qt_to_ignore > 0:
                self._qt_to_ignore -= 1
                self.stats.qt_ignored += 1
                return None
            self._stop_stream()
            self.state = "idle"
            return self._reply(conn, line, "00")
        if name == "RS":
            self._stop_stream()
            self.state = "idle"
            self._clock_epoch, self._clock_offset_ms = self.now(), 0
            return self._reply(conn, line, "00")
        if name == "RB":
            t = self.now()
            if t - self._last_rb <= 1.0:
                self._last_rb = -math.inf
                self._reply(conn, line, "00")
                self._spawn(self.reboot())
                return None
            self._last_rb = t
            return self._reply(conn, line, "01")
        if name == "TM":
            return self._time_sync(conn, line, params)
        if name in STREAM_COMMANDS or name in SINGLE_COMMANDS:
            return await self._measure(conn, line, name, params, string)
        return self._reply(conn, line, _UNSUPPORTED.get(name, "0E"))

    def _time_sync(self, conn: _Conn, line: bytes, params: bytes) -> None:
        code = params.decode("ascii", "replace")
        if code == "0":
            if self.state == "streaming":
                return self._reply(conn, line, "10")
            if self.now() < self._tm_refuse_until:
                return self._reply(conn, line, "0M")
            if self.state == "time_sync":
                return self._reply(conn, line, "02")
            self.state = "time_sync"
            return self._reply(conn, line, "00")
        if code == "1":
            if self.state != "time_sync":
                return self._reply(conn, line, "04")
            ts = encode_values(np.array([self.clock_ms()]), 4)
            return self._reply(conn, line, "00", ts + bytes([(sum(ts) & 0x3F) + 0x30]) + b"\n")
        if code == "2":
            if self.state != "time_sync":
                return self._reply(conn, line, "03")
            self.state = "idle"
            return self._reply(conn, line, "00")
        return self._reply(conn, line, "01")

    def _check_scan_params(self, name: str, params: bytes) -> tuple[str, tuple[int, ...]]:
        need = 13 if name in STREAM_COMMANDS else 10
        if len(params) < need:
            return "0H", ()
        if len(params) > need:
            return "0D", ()
        fields = [(0, 4, "01"), (4, 8, "02"), (8, 10, "03")] + ([(10, 11, "06"), (11, 13, "07")] if need == 13 else [])
        vals = []
        for a, b, err in fields:
            if not params[a:b].isdigit():
                return err, ()
            vals.append(int(params[a:b]))
        start, end = vals[0], vals[1]
        if start < int(self.params["AMIN"]) or end > int(self.params["AMAX"]):
            return "04", ()
        if end < start:
            return "05", ()
        return "00", tuple(vals)

    async def _measure(self, conn: _Conn, line: bytes, name: str, params: bytes, string: bytes) -> None:
        status, vals = self._check_scan_params(name, params)
        if status != "00":
            return self._reply(conn, line, status)
        if self.state == "time_sync":
            return self._reply(conn, line, "10")
        if name in SINGLE_COMMANDS:
            if self.state not in ("laser_on", "streaming"):
                return self._reply(conn, line, "10")
            start, end, cluster = vals
            t0 = math.ceil(self.now() / self.scan_period) * self.scan_period
            await self._sleep_until(t0 + self.scan_period)
            payload = self._scan_payload(name, t0, start, end, cluster)
            return self._reply(conn, line, "00", payload)
        self._stop_stream()
        self._reply(conn, line, "00")
        self.state = "streaming"
        conn.stream = self._spawn(self._stream(conn, name, vals, line))
        return None

    # -- streaming -----------------------------------------------------------------------------------
    def _scan_values(self, name: str, t: float, start: int, end: int, cluster: int):
        r, inten = self.scan_source(t)
        r = np.asarray(r, np.float64)
        inten = np.asarray(inten, np.float64)
        if r.ndim == 1:
            r, inten = r[:, None], inten[:, None]
        a = int(self.params["AMIN"])
        r, inten = r[start - a:end - a + 1], inten[start - a:end - a + 1]
        dmin, dmax = int(self.params["DMIN"]), int(self.params["DMAX"])
        first = ranges_to_codes(r[:, 0], dmin, dmax)
        if value_width(name) == 2:  # MS/GS: 2-char values saturate at 4095 mm
            first = np.minimum(first, 4095)
        ints = np.clip(np.rint(np.nan_to_num(inten, nan=0.0, posinf=0.0)), 0, (1 << 18) - 1).astype(np.int64)
        c = max(cluster, 1)
        if c > 1:  # a cluster reports the minimum valid reading of its steps (first echo only)
            n = expected_steps(start, end, c)
            pad = n * c - first.size
            f = np.concatenate([first, np.full(pad, 1)]).reshape(n, c)
            i = np.concatenate([ints[:, 0], np.zeros(pad, np.int64)]).reshape(n, c)
            valid = f >= dmin
            key = np.where(valid, f, f + (1 << 30))
            k = np.argmin(key, axis=1)
            return np.take_along_axis(f, k[:, None], 1)[:, 0], np.take_along_axis(i, k[:, None], 1)[:, 0]
        if name[0] in "NH":
            extra = r[:, 1:]
            with np.errstate(invalid="ignore"):
                ok = np.isfinite(extra) & (extra * 1000 >= dmin) & (extra * 1000 <= dmax)
            mm = np.where(ok, np.rint(np.nan_to_num(extra) * 1000), -1).astype(np.int64)
            # echoes must be contiguous: drop an extra echo that follows an absent one
            ok_run = np.cumprod(ok, axis=1).astype(bool)
            d = np.column_stack([first, np.where(ok_run, mm, -1)])
            i = np.column_stack([ints[:, 0], np.where(ok_run, ints[:, 1:], -1)])
            return d, i
        return first, ints[:, 0]

    def _scan_payload(self, name: str, t0: float, start: int, end: int, cluster: int) -> bytes:
        d, i = self._scan_values(name, t0, start, end, cluster)
        return encode_scan_payload(name, self.clock_ms(t0), d, i if name in ("ME", "GE", "NE", "HE") else None)

    async def _stream(self, conn: _Conn, name: str, vals: tuple[int, ...], line: bytes) -> None:
        start, end, cluster, skip, count = vals
        period = self.scan_period
        echo_head = line[:len(name) + 11]
        echo_tail = line[len(name) + 13:]
        sweep = math.ceil(self.now() / period)
        produced = sent = 0
        f = self.faults
        try:
            while not conn.closed:
                t0 = sweep * period
                sweep += 1
                await self._sleep_until(t0 + period)
                late = int((self.now() - (t0 + period)) / period)
                if late > 4:  # the host machine fell behind: skip the sweeps it missed (counted)
                    self.stats.overruns += late
                    sweep += late
                    continue
                if self.now() < self._silent_until:
                    continue
                produced += 1
                if (produced - 1) % (skip + 1):
                    continue
                n = self._scan_no
                self._scan_no += 1
                if f.reboot_at == n:
                    self._spawn(self.reboot())
                    return
                if f.disconnect_at == n:
                    self._spawn(self.disconnect())
                    return
                if f.silence_at == n:
                    self.silence(f.silence_s)
                    continue
                if f.clock_jump_at == n:
                    self.jump_clock(f.clock_jump_s)
                remaining = max(count - sent - 1, 0) if count else 0
                echo = echo_head + b"%02d" % remaining + echo_tail
                self._emit(conn, n, name, echo, t0, start, end, cluster)
                sent += 1
                if count and sent >= count:
                    self.state = "laser_on"
                    conn.stream = None
                    return
        except asyncio.CancelledError:
            pass
        except Exception:  # a broken scan source: say so loudly, the sensor goes quiet like a hung unit
            log.exception("emulator: stream stopped, the scan source failed")

    def _emit(self, conn: _Conn, n: int, name: str, echo: bytes, t0: float, start: int, end: int,
              cluster: int) -> None:
        f = self.faults

        def hit(every: int) -> bool:
            return every > 0 and n > 0 and n % every == 0

        if hit(f.status_every):
            code = _STATUS_FAULTS[self.stats.error_statuses % len(_STATUS_FAULTS)]
            if self._write(conn, encode_reply(echo, code)):
                self.stats.error_statuses += 1
            return
        msg = encode_reply(echo, "99", self._scan_payload(name, t0, start, end, cluster))
        stamp = self.clock_ms(t0)
        if hit(f.checksum_every) or hit(f.drop_every):
            head = len(echo) + 1 + 4 + 6  # echo, status line, timestamp line
            body = np.frombuffer(msg, np.uint8)[head:-1]
            if hit(f.checksum_every):
                ends = head + np.flatnonzero(body == 0x0A)  # LF of each data line
                k = int(ends[self._rng.integers(ends.size)]) - 1  # its checksum char
                b = bytearray(msg)
                b[k] = 0x30 + ((b[k] - 0x30 + 1 + int(self._rng.integers(62))) % 64)
                msg = bytes(b)
            else:
                cand = head + np.flatnonzero(body != 0x0A)
                k = int(cand[self._rng.integers(cand.size)])
                msg = msg[:k] + msg[k + 1:]
            if self._write(conn, msg):
                self.stats.scans_corrupted += 1
            return
        if hit(f.garbage_every):
            junk = self._rng.integers(0, 256, int(self._rng.integers(1, 41)), dtype=np.uint8).tobytes()
            if self._write(conn, junk):
                self.stats.garbage_writes += 1
                self.stats.garbage_bytes += len(junk)
        if hit(f.coalesce_every):
            conn.pending += msg
            self.stats.coalesced += 1
            ok = True
        else:
            ok = self._write(conn, msg)
        if ok:
            self.stats.scans_good += 1
            self.stats.good_stamps.append(stamp)

    # -- info ----------------------------------------------------------------------------------------
    def _version(self) -> dict[str, str]:
        return dict(UTM_30LX_EW_VERSION)

    def _pp(self) -> dict:
        return dict(self.params)

    def _ii(self) -> dict[str, str]:
        laser = self.state in ("laser_on", "streaming")
        ts = encode_values(np.array([self.clock_ms()]), 4).decode("ascii")
        stat = "Time synchronizing" if self.state == "time_sync" else "Stable 000 no error."
        return {"MODL": str(self.params["MODL"]), "LASR": "ON" if laser else "OFF",
                "SCSP": f"Initial({self.params['SCAN']}[rpm])", "MESM": "Measuring by Normal Mode",
                "SBPS": "Ethernet 100 [Mbps]", "TIME": ts, "STAT": stat}


__all__ = ["Faults", "EmulatorStats", "HokuyoEmulator", "ScanSource", "canned_scan_source", "room_scan_source",
           "ranges_to_codes", "sim_scan_source", "UTM_30LX_EW_PARAMS"]
