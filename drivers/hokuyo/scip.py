"""SCIP 2.0 codec (sans-IO): command encoding, an incremental reply parser and vectorized value decoding.

No sockets and no clocks here. :class:`ScipParser` takes bytes in any chunking and returns typed replies
(:class:`Reply`, :class:`InfoReply`, :class:`TimeReply`, :class:`ScanReply`) in wire order, with any
corrupt input reported *as values* (instances of :class:`drivers.hokuyo.errors.ScipProtocolError`) next to
them; it resynchronises at the next message and never raises on input.

Distances are integers in millimetres as sent by the sensor; :func:`distances_to_metres` maps them to
metres with the error codes turned into NaN (invalid) or +inf (no return).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from drivers.hokuyo.scip_jit import decode_multi, echo_intensities, echo_metres, metres, scan_frames
from drivers.hokuyo.errors import (
    BadValue,
    ChecksumError,
    GarbageData,
    ScipProtocolError,
    TruncatedMessage,
    UnexpectedEcho,
    status_error,
)

LINE_PAYLOAD = 64  # payload characters per data line (plus one checksum character)
MAX_STRING = 16  # longest ";string" the sensor echoes
TIMESTAMP_MOD = 1 << 24  # the sensor clock is 24-bit milliseconds
MAX_ECHOES = 3  # echoes per step on the UTM-30LX-EW

STREAM_COMMANDS = ("MD", "MS", "ME", "ND", "NE")
SINGLE_COMMANDS = ("GD", "GS", "GE", "HD", "HE")
SCAN_COMMANDS = STREAM_COMMANDS + SINGLE_COMMANDS
INFO_COMMANDS = ("VV", "PP", "II")

_STRING_RE = re.compile(rb"[A-Za-z0-9 ._+@]{0,16}")
# Echoes of known commands (used to find a message start, also after garbage on the same line).
_KNOWN_ECHO_RE = re.compile(
    rb"(?:(?P<stream>[MN][DSE])(?P<sp>\d{13})|(?P<single>[GH][DSE])(?P<gp>\d{10})|"
    rb"(?P<plain>VV|PP|II|BM|QT|RS|RT|RB|%ST|%SL)|(?P<tm>TM)(?P<tp>\d)|SS\d{6}|CR\d{2}|HS\d)"
    rb"(?:;(?P<string>[ -~]{0,16}))?"
)
_GENERIC_ECHO_RE = re.compile(rb"%?[A-Z]{2}[ -~]{0,40}")
_STATUS_RE = re.compile(rb"[0-9A-Z]{2}")
_MAX_ECHO_LEN = 3 + 13 + 1 + MAX_STRING
_MAX_LINE = 4096  # longer partial lines are line noise
_MAX_PAYLOAD_LINES = 2048  # 1081 steps x 3 echoes x (6 + 1) chars / 64 is about 360 lines


# ---------------------------------------------------------------------------------------------- values
def checksum(data: bytes) -> int:
    """SCIP checksum character (as an int) of ``data``: (sum of bytes & 0x3F) + 0x30."""
    return (sum(data) & 0x3F) + 0x30


def encode_int(value: int, width: int) -> bytes:
    """One value in ``width`` 6-bit characters (most significant first). ValueError if it does not fit."""
    if width not in (2, 3, 4) or not 0 <= value < 1 << (6 * width):
        raise ValueError(f"cannot encode {value} in {width} SCIP characters")
    return bytes(((value >> (6 * (width - 1 - k))) & 0x3F) + 0x30 for k in range(width))


def encode_values(values: np.ndarray, width: int) -> bytes:
    """Vectorized :func:`encode_int` of an integer array (any shape, C order), concatenated."""
    v = np.asarray(values, dtype=np.int64).ravel()
    if v.size and (v.min() < 0 or v.max() >= 1 << (6 * width)):
        raise ValueError(f"values out of range for {width}-character encoding")
    shifts = 6 * np.arange(width - 1, -1, -1)
    chars = ((v[:, None] >> shifts) & 0x3F) + 0x30
    return chars.astype(np.uint8).tobytes()


def decode_values(data: bytes | np.ndarray, width: int) -> np.ndarray:
    """Vectorized decoding of concatenated ``width``-character values -> int array.

    Raises BadValue if the length is not a multiple of ``width`` or a character is outside '0'..'o'.
    """
    a = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    if a.size % width:
        raise BadValue(f"{a.size} data characters are not a whole number of {width}-character values")
    b = a - np.uint8(0x30)  # characters below '0' wrap around to large values
    if b.size and b.max() > 0x3F:
        raise BadValue("data character outside the SCIP 6-bit alphabet")
    b = b.reshape(-1, width).astype(np.int64 if width == 4 else np.int32)
    out = b[:, 0]
    for k in range(1, width):
        out <<= 6
        out |= b[:, k]
    return out


def decode_timestamp(chars: bytes) -> int:
    """A 4-character timestamp -> milliseconds (BadValue if a character is outside the alphabet)."""
    v = 0
    for c in chars:
        d = c - 0x30
        if not 0 <= d <= 0x3F:
            raise BadValue("timestamp character outside the SCIP 6-bit alphabet")
        v = (v << 6) | d
    return v


def data_lines(payload: bytes) -> bytes:
    """Cut ``payload`` into SCIP data lines: 64 chars + checksum char + LF each, last line shorter."""
    a = np.frombuffer(payload, np.uint8)
    n = a.size
    if n == 0:
        return b""
    full, rest = divmod(n, LINE_PAYLOAD)
    lines = -(-n // LINE_PAYLOAD)
    out = np.empty(n + 2 * lines, np.uint8)
    body = out[:full * (LINE_PAYLOAD + 2)].reshape(full, LINE_PAYLOAD + 2)
    body[:, :LINE_PAYLOAD] = a[:full * LINE_PAYLOAD].reshape(full, LINE_PAYLOAD)
    # (sum & 0x3F) + 0x30: the sum mod 256 has the same low 6 bits
    body[:, LINE_PAYLOAD] = (body[:, :LINE_PAYLOAD].sum(axis=1, dtype=np.uint8) & 0x3F) + 0x30
    body[:, LINE_PAYLOAD + 1] = 0x0A
    if rest:
        tail = a[full * LINE_PAYLOAD:]
        out[-rest - 2:-2] = tail
        out[-2] = (int(tail.sum(dtype=np.uint8)) & 0x3F) + 0x30
        out[-1] = 0x0A
    return out.tobytes()


def status_line(code: str) -> bytes:
    """Status line with its checksum and LF, e.g. ``00P\\n``."""
    c = code.encode("ascii")
    return c + bytes([checksum(c)]) + b"\n"


def info_line(key: str, value: str) -> bytes:
    """``KEY:VALUE;C`` line (checksum over ``KEY:VALUE``) with LF."""
    body = f"{key}:{value}".encode("ascii")
    return body + b";" + bytes([checksum(body)]) + b"\n"


# --------------------------------------------------------------------------------------------- commands
def encode_command(command: str, params: str = "", string: str = "") -> bytes:
    """A host -> sensor command line ending in LF, e.g. ``encode_command("ME", "0000108001000")``.

    command: two capital letters or ``%`` + two; params: digits; string: up to 16 of letters, digits,
    space and ``. _ + @`` (echoed back by the sensor). ValueError on anything else.
    """
    if not re.fullmatch(r"%?[A-Z]{2}", command):
        raise ValueError(f"SCIP command must be 2 capital letters or % + 2, got {command!r}")
    if not re.fullmatch(r"[0-9]*", params):
        raise ValueError(f"SCIP parameters must be digits, got {params!r}")
    if not _STRING_RE.fullmatch(string.encode("ascii", "replace")):
        raise ValueError(f"SCIP string must be <= 16 of [A-Za-z0-9 ._+@], got {string!r}")
    line = command + params + (";" + string if string else "")
    return line.encode("ascii") + b"\n"


def scan_params(start: int, end: int, cluster: int = 1, skip: int | None = None,
                count: int | None = None) -> str:
    """Parameter digits of a scan command: ``ssss eeee cc`` (+ ``i nn`` for streams)."""
    if not (0 <= start <= end <= 9999 and 0 <= cluster <= 99):
        raise ValueError(f"bad scan range start={start} end={end} cluster={cluster}")
    p = f"{start:04d}{end:04d}{cluster:02d}"
    if skip is not None:
        if not (0 <= skip <= 9 and count is not None and 0 <= count <= 99):
            raise ValueError(f"bad stream options skip={skip} (0-9) count={count} (0-99)")
        p += f"{skip:01d}{count:02d}"
    return p


# ------------------------------------------------------------------------------------------------ types
@dataclass(frozen=True)
class Echo:
    """The echo line of a reply: the command as the sensor received it."""

    raw: bytes
    command: str
    params: str = ""
    string: str = ""


@dataclass(frozen=True)
class Reply:
    """A complete reply: echo, 2-char status and the checksum-verified payload lines (without checksum)."""

    echo: Echo
    status: str
    payload: tuple[bytes, ...] = ()

    @property
    def command(self) -> str:
        return self.echo.command

    def raise_for_status(self, ok: Iterable[str] = ("00",)) -> Reply:
        """Return self if the status is in ``ok``, else raise the specific ScipStatusError."""
        if self.status not in ok:
            raise status_error(self.status, self.echo.raw.decode("ascii", "replace"))
        return self


@dataclass(frozen=True)
class InfoReply(Reply):
    """VV / PP / II: ``fields`` maps KEY to the VALUE string (which may contain ``;`` and ``:``)."""

    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class TimeReply(Reply):
    """TM1: the sensor time in milliseconds (24-bit)."""

    time_ms: int = 0


@dataclass(frozen=True)
class ScanReply(Reply):
    """A scan (status 99 in a stream, 00 for a single GD/GE/...).

    distances: int32 (n,) millimetres or error codes (first echo); intensities: (n,) or None.
    multi / multi_intensities: (n, 3) all echoes for ND/NE/HD/HE (-1 where a step has fewer echoes).
    start/end/cluster: the step window of the command; skip/remaining: stream fields (else 0).
    """

    timestamp_ms: int = 0
    distances: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    intensities: np.ndarray | None = None
    multi: np.ndarray | None = None
    multi_intensities: np.ndarray | None = None
    start: int = 0
    end: int = 0
    cluster: int = 1
    skip: int = 0
    remaining: int = 0

    @property
    def n_steps(self) -> int:
        return int(self.distances.shape[0])


ParseItem = Reply | ScipProtocolError


# ----------------------------------------------------------------------------------------- data decode
def value_width(command: str) -> int:
    """Characters per value of a scan command (2 for MS/GS, else 3)."""
    return 2 if command in ("MS", "GS") else 3


def expected_steps(start: int, end: int, cluster: int) -> int:
    """Number of values a scan over steps start..end with ``cluster`` returns (a partial last cluster counts)."""
    c = max(cluster, 1)
    return (end - start) // c + 1


def decode_scan_data(command: str, data: bytes | np.ndarray) -> tuple[np.ndarray, np.ndarray | None,
                                                                      np.ndarray | None, np.ndarray | None]:
    """Decode the joined payload of a scan (bytes or uint8 array) -> (distances, intensities, multi,
    multi_intensities)."""
    width = value_width(command)
    with_intensity = command in ("ME", "GE", "NE", "HE")
    rec = width * (2 if with_intensity else 1)
    a = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    if command[0] in "NH":
        ok, multi, mint = decode_multi(a, width, 2 if with_intensity else 1, MAX_ECHOES)
        if ok:  # well formed (the compiled fast path); else the code below says what is wrong
            return multi[:, 0].copy(), (mint[:, 0].copy() if with_intensity else None), multi, \
                (mint if with_intensity else None)
        amp = a == 0x26
        chars = a[~amp]
        if chars.size % rec:
            raise BadValue(f"{command}: {chars.size} data characters are not whole echoes", command=command)
        nrec = chars.size // rec
        if nrec == 0:
            raise BadValue(f"{command}: no data", command=command)
        orig = np.flatnonzero(~amp)[::rec]
        amp_at = np.flatnonzero(amp)
        if amp_at.size:
            starts = np.zeros(a.size + 1, bool)  # the first character of each echo (one past the end: none)
            starts[orig] = True
            if amp_at[0] == 0 or not starts[amp_at + 1].all():
                raise BadValue(f"{command}: '&' not followed by an echo", command=command)
        extra = np.zeros(nrec, bool)
        extra[1:] = amp[orig[1:] - 1]
        vals = decode_values(chars, width).reshape(nrec, -1)
        step = np.cumsum(~extra) - 1
        first = np.flatnonzero(~extra)
        echo = np.arange(nrec) - first[step]
        if echo.max() >= MAX_ECHOES:
            raise BadValue(f"{command}: more than {MAX_ECHOES} echoes in a step", command=command)
        n = first.size
        multi = np.full((n, MAX_ECHOES), -1, np.int32)
        multi[step, echo] = vals[:, 0]
        mint = None
        if with_intensity:
            mint = np.full((n, MAX_ECHOES), -1, np.int32)
            mint[step, echo] = vals[:, 1]
        return multi[:, 0].copy(), (mint[:, 0].copy() if mint is not None else None), multi, mint
    vals = decode_values(a, width)
    if with_intensity:
        if vals.size % 2:
            raise BadValue(f"{command}: odd number of distance/intensity values", command=command)
        vals = vals.reshape(-1, 2)
        return vals[:, 0].astype(np.int32), vals[:, 1].astype(np.int32), None, None
    return vals.astype(np.int32), None, None, None


def distances_to_metres(mm: np.ndarray, dmin: int, dmax: int) -> np.ndarray:
    """Millimetres -> metres (REP 117). Code 1 ("no object in range") and readings above ``dmax`` are
    +inf (no return); other values below ``dmin`` (error codes 0, 2..) and -1 (absent echo) are NaN."""
    mm = np.asarray(mm)
    if mm.dtype.kind == "i" and mm.ndim in (1, 2) and mm.size:  # the decoder's output: the compiled loop
        return metres(mm.astype(np.int64, copy=False).reshape(mm.shape[0], -1), dmin, dmax).reshape(mm.shape)
    r = mm.astype(np.float64) * 1e-3
    r[mm < dmin] = np.nan
    r[(mm == 1) | (mm > dmax)] = np.inf
    return r


def further_echoes(multi: np.ndarray, multi_intensities: np.ndarray | None, dmin: int,
                   dmax: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The echoes after the first of a multi-echo reply: (metres (steps, k - 1) as :func:`distances_to_metres`,
    intensities (steps, k - 1) float64 with NaN where the echo is absent, or None without intensities)."""
    if multi.dtype.kind == "i" and multi.ndim == 2 and (multi_intensities is None or (
            multi_intensities.dtype.kind == "i" and multi_intensities.shape == multi.shape)):
        return echo_metres(multi, dmin, dmax), \
            None if multi_intensities is None else echo_intensities(multi, multi_intensities)
    echoes = distances_to_metres(multi[:, 1:], dmin, dmax)
    if multi_intensities is None:
        return echoes, None
    return echoes, np.where(multi[:, 1:] >= 0, multi_intensities[:, 1:], np.nan)


def warm_up() -> None:
    """Load (or, the first time on a machine, compile: seconds, longer than a client's scan watchdog) the
    compiled decoders now, with the argument types a stream gives them, rather than at the first scan."""
    scan_frames(np.frombuffer(b"\n\n", np.uint8), True, LINE_PAYLOAD)
    for command in ("NE", "ND"):
        _, _, multi, mint = decode_scan_data(command, np.frombuffer(encode_values(np.arange(4), 3), np.uint8).copy())
        distances_to_metres(multi[:, 0].copy(), 1, 2)
        further_echoes(multi, mint, 1, 2)


# ------------------------------------------------------------------------------------------------ parser
_KNOWN_ECHO_END_RE = re.compile(_KNOWN_ECHO_RE.pattern + rb"\Z")


def _find_echo(line: bytes, strict: bool) -> tuple[int, re.Match | None] | None:
    """Locate an echo in ``line``: (garbage prefix length, match of a known command or None=generic)."""
    m = _KNOWN_ECHO_END_RE.search(line)  # leftmost start of a known echo running to the end of the line
    if m is not None:
        start = m.start()
        # A partial echo left without its line end (``MS...;``) glues onto the next reply's echo, which
        # then reads as its string field: resynchronise at the last known echo that forms the string.
        while (string := _KNOWN_ECHO_RE.fullmatch(line, start)) is not None and string.group("string"):
            nxt = _KNOWN_ECHO_RE.fullmatch(line, string.start("string"))
            if nxt is None:
                break
            start = string.start("string")
        return start, _KNOWN_ECHO_RE.fullmatch(line, start)
    if not strict and len(line) <= _MAX_ECHO_LEN + 8 and _GENERIC_ECHO_RE.fullmatch(line):
        return 0, None
    return None


def _is_status(line: bytes) -> bool:
    return len(line) == 3 and _STATUS_RE.fullmatch(line, 0, 2) is not None and line[2] == checksum(line[:2])


def _make_echo(raw: bytes, m: re.Match | None) -> Echo:
    text = raw.decode("ascii", "replace")
    if m is None:
        head, _, string = text.partition(";")
        cmd = head[:3] if head.startswith("%") else head[:2]
        return Echo(raw, cmd, head[len(cmd):], string)
    head, _, string = text.partition(";")
    if m.group("tm"):
        return Echo(raw, "TM", m.group("tp").decode(), string)
    cmd = head[:3] if head.startswith("%") else head[:2]
    return Echo(raw, cmd, head[len(cmd):], string)


@dataclass
class _Msg:
    echo: Echo
    status: str
    lines: list[bytes] = field(default_factory=list)
    overflow: bool = False


class ScipParser:
    """Incremental SCIP reply parser. ``feed(bytes) -> list[Reply | ScipProtocolError]``.

    Works line by line with one line of look-ahead: a message starts with an echo line followed by a
    valid status line, collects payload lines and ends at an empty line. If a message start shows up
    inside a message (a lost terminator), the broken message is reported and the new one is kept.
    Memory is bounded: over-long lines and messages are reported and dropped.
    """

    def __init__(self, *, verify_checksums: bool = True) -> None:
        self.verify_checksums = verify_checksums
        self._partial = bytearray()
        self._lines: list[bytes] = []
        self._pos = 0  # next unprocessed line in _lines
        self._msg: _Msg | None = None
        self._garbage = bytearray()
        self._garbage_n = 0
        self._out: list[ParseItem] = []

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a line or message (bounded)."""
        pending = self._lines[self._pos:] + (self._msg.lines if self._msg else [])
        return len(self._partial) + sum(len(x) + 1 for x in pending)

    def reset(self) -> None:
        """Forget any partial input (e.g. after reconnecting)."""
        self.__init__(verify_checksums=self.verify_checksums)

    def feed(self, data: bytes) -> list[ParseItem]:
        """Consume bytes; return the replies completed by them and the errors found, in wire order."""
        if data:
            self._partial += data
            if self._msg is None and self._pos >= len(self._lines) and not self._garbage_n:
                self._fast_scans()
            if b"\n" in data:
                parts = bytes(self._partial).split(b"\n")
                self._partial = bytearray(parts.pop())
                self._lines.extend(parts)
            if len(self._partial) > _MAX_LINE:
                self._add_garbage(bytes(self._partial))
                self._partial.clear()
        self._run()
        del self._lines[:self._pos]
        self._pos = 0
        self._flush_garbage_if_idle()
        out, self._out = self._out, []
        return out

    def _fast_scans(self) -> None:
        """Fast path for the common case: whole, well-formed scan messages at the head of the buffer.

        Anything unusual (another command, short lines inside, a bad checksum) is left to the line-by-line
        state machine, which gives the same result for good messages and reports bad ones."""
        buf = self._partial
        if len(buf) < 16:
            return
        frames, data, offsets = scan_frames(np.frombuffer(bytes(buf), np.uint8), self.verify_checksums,
                                            LINE_PAYLOAD)
        done = 0  # bytes consumed
        for k, (start, i1, i2, e) in enumerate(frames.tolist()):
            echo_raw = bytes(buf[start:i1])
            m = _KNOWN_ECHO_RE.fullmatch(echo_raw)
            status = bytes(buf[i1 + 1:i2])
            if m is None or not (m.group("stream") or m.group("single")) or not _is_status(status) \
                    or status[:2] not in (b"99", b"00"):
                break
            if m.group("string") and _KNOWN_ECHO_RE.fullmatch(echo_raw, m.start("string")):
                break  # an echo glued to a partial one: the state machine resynchronises
            try:
                self._out.append(self._scan_from(_make_echo(echo_raw, m), status[:2].decode("ascii"),
                                                 bytes(buf[i2 + 1:i2 + 5]), data[offsets[k]:offsets[k + 1]]))
            except ScipProtocolError as exc:
                self._out.append(exc)
            done = e + 1
        if done:
            del buf[:done]

    # -- state machine ------------------------------------------------------------------------------
    def _run(self) -> None:
        lines = self._lines
        while self._pos < len(lines):
            pos = self._pos
            msg = self._msg
            if msg is None:
                line = lines[pos]
                if not line:
                    self._pos += 1
                    self._add_garbage(b"\n")
                    continue
                if pos + 1 >= len(lines):
                    return
                found = _find_echo(line, strict=False)
                if found is not None and _is_status(lines[pos + 1]):
                    g, m = found
                    if g:
                        self._add_garbage(line[:g])
                    self._flush_garbage()
                    self._msg = _Msg(_make_echo(line[g:], m), lines[pos + 1][:2].decode("ascii"))
                    self._pos += 2
                else:
                    self._add_garbage(line + b"\n")
                    self._pos += 1
                continue
            # Payload: take every line up to the next blank one at once, unless a message starts inside.
            try:
                k = lines.index(b"", pos)
            except ValueError:
                k = len(lines)
            seg = lines[pos:k]
            cut = None
            if seg:
                lens = np.fromiter(map(len, seg), np.int64, len(seg))
                # an intact full data line (64 + checksum) holds no echo; any other line might (after noise)
                full = np.flatnonzero(lens == LINE_PAYLOAD + 1)
                cand = lens != LINE_PAYLOAD + 1
                if full.size:
                    rows = np.frombuffer(b"".join([seg[j] for j in full.tolist()]), np.uint8).reshape(-1, LINE_PAYLOAD + 1)
                    sums = rows[:, :LINE_PAYLOAD].sum(axis=1, dtype=np.int64)
                    cand[full[((sums & 0x3F) + 0x30) != rows[:, LINE_PAYLOAD]]] = True
                # A cut message glued to the next echo can form a line of full length whose checksum
                # passes by chance: check any line followed by a status-sized one, or last in the buffer.
                cand[np.flatnonzero(lens[1:] == 3)] = True
                if k == len(lines):
                    cand[-1] = True
                for j in np.flatnonzero(cand).tolist():
                    if _find_echo(seg[j], strict=True) is None:
                        continue
                    if pos + j + 1 >= len(lines):
                        cut = ("wait", j)
                        break
                    if _is_status(lines[pos + j + 1]):
                        cut = ("split", j)
                        break
            if cut is not None:
                self._take(msg, seg[:cut[1]])
                self._pos = pos + cut[1]
                if cut[0] == "wait":
                    return
                self._msg = None
                self._out.append(TruncatedMessage(
                    f"{msg.echo.command}: message cut short, next message began inside it",
                    command=msg.echo.command, data=msg.echo.raw))
                continue
            self._take(msg, seg)
            self._pos = k
            if k < len(lines):
                self._pos = k + 1
                self._msg = None
                self._finish(msg)

    @staticmethod
    def _take(msg: _Msg, seg: list[bytes]) -> None:
        room = _MAX_PAYLOAD_LINES - len(msg.lines)
        if len(seg) > room:
            msg.overflow = True
            seg = seg[:max(room, 0)]
        msg.lines.extend(seg)

    def _add_garbage(self, data: bytes) -> None:
        if len(self._garbage) < 64:
            self._garbage += data[: 64 - len(self._garbage)]
        self._garbage_n += len(data)

    def _flush_garbage(self) -> None:
        if self._garbage_n:
            self._out.append(GarbageData(f"{self._garbage_n} bytes of line noise between messages",
                                         data=bytes(self._garbage), nbytes=self._garbage_n))
            self._garbage.clear()
            self._garbage_n = 0

    def _flush_garbage_if_idle(self) -> None:
        # Report noise once no message start can follow it within the buffered input.
        if self._garbage_n and self._msg is None and self._pos >= len(self._lines) and not self._partial:
            self._flush_garbage()

    # -- message decoding ---------------------------------------------------------------------------
    def _finish(self, msg: _Msg) -> None:
        try:
            self._out.append(self._decode(msg))
        except ScipProtocolError as exc:
            self._out.append(exc)

    def _decode(self, msg: _Msg) -> Reply:
        echo, cmd = msg.echo, msg.echo.command
        if msg.overflow:
            raise TruncatedMessage(f"{cmd}: message longer than {_MAX_PAYLOAD_LINES} lines", command=cmd,
                                   data=echo.raw)
        if cmd in INFO_COMMANDS and msg.status == "00":
            return InfoReply(echo, msg.status, tuple(msg.lines), self._info_fields(cmd, msg.lines))
        lines = msg.lines
        joined = self._check(cmd, lines)
        if cmd in SCAN_COMMANDS and joined is not None and msg.status in ("00", "99"):
            return self._scan(echo, msg.status, lines, *joined)
        if cmd in SCAN_COMMANDS and msg.status == "99":
            raise TruncatedMessage(f"{cmd}: scan message without data", command=cmd, data=echo.raw)
        payload = tuple(x[:-1] for x in lines)
        if cmd == "TM" and echo.params == "1" and msg.status == "00":
            if len(payload) != 1 or len(payload[0]) != 4:
                raise TruncatedMessage("TM1: expected one 4-character time line", command=cmd, data=echo.raw)
            return TimeReply(echo, msg.status, payload, int(decode_values(payload[0], 4)[0]))
        return Reply(echo, msg.status, payload)

    def _check(self, cmd: str, lines: list[bytes]) -> tuple[np.ndarray, np.ndarray] | None:
        """Verify the checksum of every payload line (vectorized); ChecksumError names the first bad one.

        Returns the joined lines as uint8 and the line lengths (None when there are no lines)."""
        if not lines:
            return None
        lens = np.fromiter(map(len, lines), np.int64, len(lines))
        a = np.frombuffer(b"".join(lines), np.uint8)
        if not self.verify_checksums:
            return a, lens
        if lens.min() < 2:
            raise ChecksumError(f"{cmd}: data line too short to hold a checksum", command=cmd)
        ends = np.cumsum(lens)
        sums = np.add.reduceat(a, ends - lens, dtype=np.int64) - a[ends - 1]
        bad = ((sums & 0x3F) + 0x30) != a[ends - 1]
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ChecksumError(f"{cmd}: {int(bad.sum())} data line(s) failed the checksum (first: line {k + 1})",
                                command=cmd, data=lines[k])
        return a, lens

    def _info_fields(self, cmd: str, lines: list[bytes]) -> dict[str, str]:
        fields: dict[str, str] = {}
        for x in lines:
            # KEY:VALUE;C -- the checksum is the last char, the separator the one before; VALUE may hold ; and :
            if len(x) < 4 or x[-2:-1] != b";" or b":" not in x[:-2]:
                raise BadValue(f"{cmd}: malformed info line", command=cmd, data=x)
            body = x[:-2]
            if self.verify_checksums and x[-1] != checksum(body):
                raise ChecksumError(f"{cmd}: info line failed its checksum", command=cmd, data=x)
            key, _, value = body.decode("ascii", "replace").partition(":")
            fields[key] = value
        return fields

    def _scan(self, echo: Echo, status: str, lines: list[bytes], a: np.ndarray, lens: np.ndarray) -> ScanReply:
        cmd = echo.command
        if len(lines[0]) != 5:
            raise TruncatedMessage(f"{cmd}: timestamp line has {len(lines[0]) - 1} chars, expected 4",
                                   command=cmd, data=lines[0])
        keep = np.ones(a.size, bool)
        keep[: lens[0]] = False  # the timestamp line
        keep[np.cumsum(lens) - 1] = False  # checksum characters
        return self._scan_from(echo, status, lines[0][:4], a[keep])

    @staticmethod
    def _scan_from(echo: Echo, status: str, ts_chars: bytes | np.ndarray, data: np.ndarray) -> ScanReply:
        cmd, p = echo.command, echo.params
        need = 13 if cmd in STREAM_COMMANDS else 10
        if len(p) != need or not p.isdigit():
            raise UnexpectedEcho(f"{cmd}: echo parameters {p!r} are not a scan command's", command=cmd,
                                 data=echo.raw)
        start, end, cluster = int(p[0:4]), int(p[4:8]), int(p[8:10])
        skip, remaining = (int(p[10]), int(p[11:13])) if need == 13 else (0, 0)
        ts = decode_timestamp(bytes(ts_chars))
        try:
            dist, inten, multi, mint = decode_scan_data(cmd, data)
        except BadValue as exc:
            raise BadValue(str(exc), command=cmd, data=echo.raw) from None
        n = expected_steps(start, end, cluster) if end >= start else -1
        if dist.shape[0] != n:
            raise TruncatedMessage(f"{cmd}: {dist.shape[0]} steps decoded, {n} expected", command=cmd,
                                   data=echo.raw)
        return ScanReply(echo, status, (), ts, dist, inten, multi, mint, start, end, max(cluster, 1), skip,
                         remaining)


# --------------------------------------------------------------------------------------------- encoding
def encode_reply(echo: bytes, status: str, payload: bytes = b"") -> bytes:
    """A whole reply: echo line, status line, ready-made payload lines, blank line."""
    return echo + b"\n" + status_line(status) + payload + b"\n"


def encode_scan_payload(command: str, timestamp_ms: int, distances: np.ndarray,
                        intensities: np.ndarray | None = None) -> bytes:
    """Payload lines of a scan: 4-char timestamp line then data lines.

    distances: (n,) int mm, or (n, e) for multi-echo commands with -1 where a step has fewer echoes
    (the first echo must be present); intensities: same shape, for ME/GE/NE/HE.
    """
    width = value_width(command)
    with_intensity = command in ("ME", "GE", "NE", "HE")
    if with_intensity and intensities is None:
        raise ValueError(f"{command} needs intensities")
    ts = encode_values(np.array([timestamp_ms % TIMESTAMP_MOD]), 4)
    d = np.asarray(distances, np.int64)
    if command[0] in "NH":
        d2 = d.reshape(d.shape[0], -1)
        present = d2 >= 0
        present[:, 0] = True
        cols = [d2]
        if with_intensity:
            cols.append(np.asarray(intensities, np.int64).reshape(d2.shape))
        vals = np.stack(cols, axis=-1)  # (n, e, k)
        n, e, k = vals.shape
        chars = np.frombuffer(encode_values(np.where(present[..., None], vals, 0), width), np.uint8)
        tok = np.empty((n, e, 1 + k * width), np.uint8)
        tok[..., 0] = 0x26  # '&'
        tok[..., 1:] = chars.reshape(n, e, k * width)
        keep = np.repeat(present[..., None], 1 + k * width, axis=2)
        keep[:, 0, 0] = False
        data = tok[keep].tobytes()
    else:
        if with_intensity:
            data = encode_values(np.stack([d, np.asarray(intensities, np.int64)], axis=-1), width)
        else:
            data = encode_values(d, width)
    return data_lines(ts) + data_lines(data)
