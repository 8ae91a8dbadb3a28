"""ARCOS/P2OS packet framing for the Pioneer 3-DX (sans-IO: bytes in, packets out; no sockets, no clocks).

Frame (both directions)::

    0xFA 0xFB | N | ID | payload ... | CK_hi CK_lo      N = 1 + len(payload) + 2

Numbers in payloads are little-endian; the checksum is big-endian: successive byte pairs of ID..payload
added as big-endian 16-bit words (mod 2**16), a leftover odd byte XORed into the low byte.

Command arguments: 0x3B + uint16 LE for a value >= 0, 0x1B + uint16 LE of the absolute value for a negative
one (sign-magnitude), 0x2B + length byte + bytes for a string. We send at most N = 200 and accept 3..255.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import IntEnum

from drivers.pioneer.errors import ChecksumError, FramingError, PacketError

HEADER = b"\xfa\xfb"
MIN_N = 3
MAX_SEND_N = 200

ARG_INT = 0x3B
ARG_NEGINT = 0x1B
ARG_STR = 0x2B

# Handshake packet IDs (the same IDs mean PULSE/OPEN/CLOSE once the connection is open).
SYNC0 = 0
SYNC1 = 1
SYNC2 = 2


class Cmd(IntEnum):
    """Client command numbers (ARCOS)."""

    PULSE = 0
    OPEN = 1
    CLOSE = 2
    ENABLE = 4
    SETA = 5
    SETV = 6
    SETO = 7
    SETRV = 10
    VEL = 11
    HEAD = 12
    DHEAD = 13
    CONFIG = 18
    ENCODER = 19
    RVEL = 21
    SETRA = 23
    SONAR = 28
    STOP = 29
    VEL2 = 32
    HOSTBAUD = 50
    ESTOP = 55


class PacketType(IntEnum):
    """Server (robot -> host) packet IDs."""

    SIP_STOPPED = 0x32
    SIP_MOVING = 0x33
    CONFIG = 0x20
    ENCODER = 0x90
    IO = 0xF0
    GYRO = 0x98


SIP_IDS = (PacketType.SIP_STOPPED, PacketType.SIP_MOVING)

# HOSTBAUD argument codes.
HOSTBAUD_CODES = {9600: 0, 19200: 1, 38400: 2, 57600: 3, 115200: 4}


def checksum(body: bytes | bytearray | memoryview) -> int:
    """ARCOS checksum of ``ID + payload`` (16-bit, see module docstring)."""
    c = 0
    n = len(body)
    for i in range(0, n - 1, 2):
        c = (c + ((body[i] << 8) | body[i + 1])) & 0xFFFF
    if n & 1:
        c ^= body[n - 1]
    return c


def build_packet(pid: int, payload: bytes = b"", *, max_n: int = MAX_SEND_N) -> bytes:
    """Frame one packet. Raises ValueError for an ID outside 0..255 or a packet longer than ``max_n``."""
    if not 0 <= pid <= 0xFF:
        raise ValueError(f"packet ID must be 0..255, got {pid}")
    n = 1 + len(payload) + 2
    if n > max_n:
        raise ValueError(f"packet too long: N = {n} > {max_n} (payload of {len(payload)} bytes)")
    body = bytes([pid]) + bytes(payload)
    ck = checksum(body)
    return HEADER + bytes([n]) + body + bytes([ck >> 8, ck & 0xFF])


def int_arg(value: int) -> bytes:
    """Integer argument in sign-magnitude form: 0x3B/0x1B then |value| as uint16 LE."""
    value = int(value)
    mag = abs(value)
    if mag > 0xFFFF:
        raise ValueError(f"integer argument out of range: |{value}| > 65535")
    return bytes([ARG_NEGINT if value < 0 else ARG_INT, mag & 0xFF, mag >> 8])


def str_arg(value: str | bytes) -> bytes:
    """String argument: 0x2B, a length byte, then the bytes (ASCII for str)."""
    data = value.encode("ascii") if isinstance(value, str) else bytes(value)
    if len(data) > 0xFF:
        raise ValueError(f"string argument too long: {len(data)} bytes > 255")
    return bytes([ARG_STR, len(data)]) + data


def command(cmd: int, arg: int | str | bytes | None = None) -> bytes:
    """A framed client command: no argument, an integer argument, or a string argument."""
    if arg is None:
        return build_packet(int(cmd))
    if isinstance(arg, bool):
        arg = int(arg)
    if isinstance(arg, int):
        return build_packet(int(cmd), int_arg(arg))
    if isinstance(arg, (str, bytes, bytearray)):
        return build_packet(int(cmd), str_arg(arg))
    raise ValueError(f"unsupported argument type {type(arg).__name__} for command {cmd}")


def vel2_value(left: int, right: int) -> int:
    """The VEL2 integer: left wheel in the high byte, right in the low, each a signed byte (Vel2Divisor units).

    Returned as a signed 16-bit value ``(left << 8) + (right & 0xFF)``, sent with the sign-magnitude rule.
    """
    for name, v in (("left", left), ("right", right)):
        if not -128 <= v <= 127:
            raise ValueError(f"VEL2 {name} wheel value must be -128..127 (units of Vel2Divisor), got {v}")
    return (int(left) << 8) + (int(right) & 0xFF)


def vel2_split(value: int) -> tuple[int, int]:
    """Inverse of :func:`vel2_value`: (left, right) signed bytes from the received signed integer."""
    raw = value & 0xFFFF
    hi, lo = raw >> 8, raw & 0xFF
    return (hi - 256 if hi > 127 else hi), (lo - 256 if lo > 127 else lo)


def parse_int_arg(payload: bytes) -> int | None:
    """The integer argument of a received command payload, or None when there is none / it is malformed."""
    if len(payload) < 3 or payload[0] not in (ARG_INT, ARG_NEGINT):
        return None
    mag = payload[1] | (payload[2] << 8)
    return -mag if payload[0] == ARG_NEGINT else mag


@dataclass(frozen=True)
class Packet:
    """One validated packet. ``stamp``: caller's time of the chunk that held the packet's first byte."""

    pid: int
    payload: bytes
    stamp: float | None = None


@dataclass
class ParserStats:
    """Counters of what the parser saw (all bytes are accounted: in packets or dropped)."""

    bytes_in: int = 0
    packets: int = 0
    dropped_bytes: int = 0
    bad_checksum: int = 0
    bad_length: int = 0
    timeouts: int = 0


class PacketParser:
    """Incremental ARCOS parser: hunts for 0xFA 0xFB, waits for N bytes, checks the checksum.

    A bad length byte or a bad checksum drops only the first header byte and re-hunts from the next one, so
    a false header in line noise cannot swallow a real packet behind it. With ``inter_byte_timeout`` set and
    times passed to :meth:`feed`, a partial packet older than the timeout is given up the same way.
    :meth:`feed` never raises on input bytes; each problem is counted in :attr:`stats` and kept (most recent
    ``keep_errors``) in :attr:`errors` as a :class:`ChecksumError` or :class:`FramingError`.
    Unknown packet IDs are returned like any other: skipping them is the decoder's business.
    """

    def __init__(self, *, inter_byte_timeout: float | None = 0.5, keep_errors: int = 16) -> None:
        self.inter_byte_timeout = inter_byte_timeout
        self.stats = ParserStats()
        self.errors: deque[PacketError] = deque(maxlen=keep_errors)
        self._buf = bytearray()
        self._base = 0  # absolute stream offset of _buf[0]
        self._marks: deque[tuple[int, float | None]] = deque()  # (absolute end offset of a chunk, its time)
        self._last_t: float | None = None

    @property
    def pending(self) -> int:
        """Bytes held back (an incomplete packet or a possible header start)."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget any partial input (e.g. after reconnecting)."""
        self.stats.dropped_bytes += len(self._buf)
        self._base += len(self._buf)
        self._buf.clear()
        self._marks.clear()

    def feed(self, data: bytes, t: float | None = None) -> list[Packet]:
        """Add received bytes (``t``: arrival time of this chunk) and return the complete valid packets."""
        out: list[Packet] = []
        if (self._buf and t is not None and self._last_t is not None and self.inter_byte_timeout is not None
                and t - self._last_t > self.inter_byte_timeout):
            self._scan(out, flush=True)
        if data:
            self._buf += data
            self.stats.bytes_in += len(data)
            self._marks.append((self._base + len(self._buf), t))
        if t is not None:
            self._last_t = t
        self._scan(out, flush=False)
        return out

    # -- internals -------------------------------------------------------------------------------------
    def _drop(self, n: int) -> None:
        del self._buf[:n]
        self._base += n
        while self._marks and self._marks[0][0] <= self._base:
            self._marks.popleft()

    def _stamp_of_first_byte(self) -> float | None:
        for end, t in self._marks:
            if end > self._base:
                return t
        return None

    def _error(self, exc: PacketError) -> None:
        self.errors.append(exc)

    def _scan(self, out: list[Packet], *, flush: bool) -> None:
        buf = self._buf
        while buf:
            i = buf.find(HEADER)
            if i < 0:
                keep = 1 if buf[-1] == HEADER[0] and not flush else 0
                self.stats.dropped_bytes += len(buf) - keep
                self._drop(len(buf) - keep)
                return
            if i:
                self.stats.dropped_bytes += i
                self._drop(i)
            if len(buf) < 3:
                if flush:
                    self._timeout()
                    continue
                return
            n = buf[2]
            if n < MIN_N:
                self.stats.bad_length += 1
                self._error(FramingError(f"length byte {n} < {MIN_N}: not a packet header, re-synchronising"))
                self.stats.dropped_bytes += 1
                self._drop(1)
                continue
            if len(buf) < 3 + n:
                if flush:
                    self._timeout()
                    continue
                return
            body = bytes(buf[3: 1 + n])
            got = (buf[1 + n] << 8) | buf[2 + n]
            want = checksum(body)
            if got != want:
                self.stats.bad_checksum += 1
                self._error(ChecksumError(
                    f"packet ID 0x{body[0]:02x} N={n}: checksum 0x{got:04x} != computed 0x{want:04x}; dropped"))
                self.stats.dropped_bytes += 1
                self._drop(1)
                continue
            out.append(Packet(body[0], body[1:], self._stamp_of_first_byte()))
            self.stats.packets += 1
            self._drop(3 + n)

    def _timeout(self) -> None:
        self.stats.timeouts += 1
        self._error(FramingError(
            f"partial packet ({len(self._buf)} bytes) timed out after {self.inter_byte_timeout} s; re-synchronising"))
        self.stats.dropped_bytes += 1
        self._drop(1)
