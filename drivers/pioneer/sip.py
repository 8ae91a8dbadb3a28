"""Typed decoding (and, for the emulator, encoding) of Pioneer server packets (sans-IO).

- Standard SIP (ID 0x32 stopped / 0x33 moving): all fixed fields, the sonar readings, and the optional tail
  (GRIP, ANPORT, ANALOG, DIGIN, DIGOUT, BATTERYX10, CHARGESTATE, ROTVEL, FAULTFLAGS) parsed field by field
  while bytes remain; anything after that is kept raw in ``extra``.
- SYNC2 reply (ID 2): robot name, class, subclass (NUL-terminated strings).
- CONFIG (0x20): every field of the ARIA layout; fields after the watchdog are optional (older
  controllers stop early).
- ENCODER (0x90): left and right raw encoder counts (int32 LE).

Values are kept in the robot's raw units here; :mod:`drivers.pioneer.odometry` converts to SI.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field, fields

from drivers.pioneer.errors import DecodeError
from drivers.pioneer.packets import SIP_IDS, Packet, PacketType, build_packet

_SIP_FIXED = struct.Struct("<HHhhhBHhHBB")  # XPOS..SONAR_COUNT: 19 bytes

# Optional tail of the standard SIP, in order: (field name, struct format).
_SIP_TAIL: tuple[tuple[str, str], ...] = (
    ("grip", "<B"), ("anport", "<B"), ("analog", "<B"), ("digin", "<B"), ("digout", "<B"),
    ("battery_x10", "<H"), ("charge_state", "<B"), ("rotvel", "<h"), ("fault_flags", "<H"),
)


@dataclass(frozen=True)
class StandardSIP:
    """Standard server information packet, raw units.

    xpos/ypos: raw u16 (only the 15 low bits valid on a real robot), x DistConvFactor -> mm.
    thpos: heading in angle units (4096 per turn). lvel/rvel: wheel speeds, mm/s. battery: 0.1 V.
    stall_bumpers: bit0 left stall, bits1-7 rear bumpers, bit8 right stall, bits9-15 front bumpers.
    control: heading setpoint (angle units). flags: bit0 motors enabled, bits1-4 sonar arrays, bit5 e-stop.
    compass: 2-degree units. sonar: (index, range in mm) of the readings new in this packet.
    rotvel: 0.1 deg/s (optional tail); battery_x10: 0.1 V (optional tail).
    """

    moving: bool
    xpos: int
    ypos: int
    thpos: int
    lvel: int
    rvel: int
    battery: int
    stall_bumpers: int = 0
    control: int = 0
    flags: int = 0
    compass: int = 0
    sonar: tuple[tuple[int, int], ...] = ()
    grip: int | None = None
    anport: int | None = None
    analog: int | None = None
    digin: int | None = None
    digout: int | None = None
    battery_x10: int | None = None
    charge_state: int | None = None
    rotvel: int | None = None
    fault_flags: int | None = None
    extra: bytes = b""

    @property
    def battery_volts(self) -> float:
        """Battery voltage (V): BATTERYX10 when present (finer), else BATTERY."""
        return (self.battery_x10 if self.battery_x10 is not None else self.battery) / 10.0

    @property
    def left_stall(self) -> bool:
        return bool(self.stall_bumpers & 0x0001)

    @property
    def right_stall(self) -> bool:
        return bool(self.stall_bumpers & 0x0100)

    @property
    def rear_bumpers(self) -> int:
        """Rear bumper bits (bit i = bumper i, 7 bits)."""
        return (self.stall_bumpers >> 1) & 0x7F

    @property
    def front_bumpers(self) -> int:
        """Front bumper bits (bit i = bumper i, 7 bits)."""
        return (self.stall_bumpers >> 9) & 0x7F

    @property
    def motors_enabled(self) -> bool:
        return bool(self.flags & 0x0001)

    @property
    def sonar_arrays(self) -> int:
        """Enabled sonar arrays (4 bits)."""
        return (self.flags >> 1) & 0x0F

    @property
    def estop(self) -> bool:
        return bool(self.flags & 0x0020)


def decode_sip(pid: int, payload: bytes) -> StandardSIP:
    """Decode a standard SIP payload (the bytes after the ID). Raises DecodeError if it is too short."""
    if pid not in SIP_IDS:
        raise DecodeError(f"packet ID 0x{pid:02x} is not a standard SIP (0x32/0x33)")
    if len(payload) < _SIP_FIXED.size:
        raise DecodeError(f"SIP too short: {len(payload)} payload bytes < {_SIP_FIXED.size}")
    (x, y, th, lv, rv, batt, sb, control, flags, compass, nson) = _SIP_FIXED.unpack_from(payload, 0)
    off = _SIP_FIXED.size
    if len(payload) < off + 3 * nson:
        raise DecodeError(f"SIP announces {nson} sonar readings but only {len(payload) - off} bytes follow")
    sonar = tuple(struct.unpack_from("<BH", payload, off + 3 * k) for k in range(nson))
    off += 3 * nson
    tail: dict[str, int] = {}
    for name, fmt in _SIP_TAIL:
        size = struct.calcsize(fmt)
        if len(payload) - off < size:
            break
        (tail[name],) = struct.unpack_from(fmt, payload, off)
        off += size
    return StandardSIP(pid == PacketType.SIP_MOVING, x, y, th, lv, rv, batt, sb, control, flags, compass,
                       sonar, extra=bytes(payload[off:]), **tail)


def encode_sip(sip: StandardSIP) -> bytes:
    """Framed SIP packet (emulator side). Tail fields are written up to the last one that is not None."""
    pid = PacketType.SIP_MOVING if sip.moving else PacketType.SIP_STOPPED
    payload = bytearray(_SIP_FIXED.pack(sip.xpos & 0xFFFF, sip.ypos & 0xFFFF, sip.thpos, sip.lvel, sip.rvel,
                                        sip.battery, sip.stall_bumpers, sip.control, sip.flags, sip.compass,
                                        len(sip.sonar)))
    for idx, rng in sip.sonar:
        payload += struct.pack("<BH", idx, rng)
    values = [getattr(sip, name) for name, _ in _SIP_TAIL]
    last = max((k for k, v in enumerate(values) if v is not None), default=-1)
    for k in range(last + 1):
        payload += struct.pack(_SIP_TAIL[k][1], values[k] or 0)
    payload += sip.extra
    return build_packet(pid, bytes(payload))


@dataclass(frozen=True)
class SyncReply:
    """The SYNC2 reply: robot name, class (``Pioneer``), subclass (``p3dx`` or ``p3dx-sh``)."""

    name: str
    robot_class: str
    subclass: str


def _split_strings(payload: bytes, count: int, what: str) -> tuple[list[str], int]:
    out, off = [], 0
    for _ in range(count):
        end = payload.find(b"\x00", off)
        if end < 0:
            raise DecodeError(f"{what}: expected {count} NUL-terminated strings, got {len(out)}")
        out.append(payload[off:end].decode("latin-1"))
        off = end + 1
    return out, off


def decode_sync2(payload: bytes) -> SyncReply:
    """Decode the SYNC2 reply payload. Raises DecodeError when the three strings are not there."""
    (name, cls, sub), _ = _split_strings(payload, 3, "SYNC2 reply")
    return SyncReply(name, cls, sub)


def encode_sync2(reply: SyncReply) -> bytes:
    payload = b"".join(s.encode("latin-1") + b"\x00" for s in (reply.name, reply.robot_class, reply.subclass))
    return build_packet(2, payload)


@dataclass(frozen=True)
class ConfigPacket:
    """CONFIG packet (0x20), every field in the order the reference client (ARIA) reads them.

    Strings are NUL-terminated. Velocities mm/s and deg/s, accelerations mm/s^2 and deg/s^2, sip_cycle and
    sonar_cycle ms, watchdog ms, low_battery and shutdown_voltage 0.1 V. host_baud/aux*_baud: HOSTBAUD codes
    (0=9600 .. 4=115200). rotvel_max/transvel_max (and the accelerations after them) are the *current*
    limits a client starts from; the *_top fields are the hardware ceilings. reset_baud == 2: the client
    may switch the serial speed with HOSTBAUD. Fields after ``watchdog`` are None when the packet ends
    before them (older controllers send less); bytes after the last field are kept raw in ``extra``.
    """

    robot_type: str
    subtype: str
    serial: str
    four_mots: int = 0
    rotvel_top: int = 0
    transvel_top: int = 0
    rotaccel_top: int = 0
    transaccel_top: int = 0
    pwm_max: int = 0
    name: str = ""
    sip_cycle: int = 100
    host_baud: int = 0
    aux_baud: int = 0
    gripper: int = 0
    front_sonar: int = 0
    rear_sonar: int = 0
    low_battery: int = 0
    revcount: int = 0
    watchdog: int = 2000
    normal_mpacs: int | None = None
    stall_val: int | None = None
    stall_count: int | None = None
    joy_vel: int | None = None
    joy_rotvel: int | None = None
    rotvel_max: int | None = None
    transvel_max: int | None = None
    rot_accel: int | None = None
    rot_decel: int | None = None
    rot_kp: int | None = None
    rot_kv: int | None = None
    rot_ki: int | None = None
    trans_accel: int | None = None
    trans_decel: int | None = None
    trans_kp: int | None = None
    trans_kv: int | None = None
    trans_ki: int | None = None
    front_bumps: int | None = None
    rear_bumps: int | None = None
    has_charger: int | None = None
    sonar_cycle: int | None = None
    reset_baud: int | None = None
    gyro_type: int | None = None
    drift_factor: int | None = None
    aux2_baud: int | None = None
    aux3_baud: int | None = None
    ticks_mm: int | None = None
    shutdown_voltage: int | None = None
    firmware_version: str | None = None
    gyro_cw: int | None = None
    gyro_ccw: int | None = None
    kinematics_delay: int | None = None
    latvel_top: int | None = None
    lataccel_top: int | None = None
    latvel_max: int | None = None
    lat_accel: int | None = None
    lat_decel: int | None = None
    charge_threshold: int | None = None
    pdb_port: int | None = None
    gyro_rate_limit: int | None = None
    high_temperature_shutdown: int | None = None
    power_bits: int | None = None
    battery_type: int | None = None
    state_of_charge_low: int | None = None
    state_of_charge_shutdown: int | None = None
    bootloader_version: str | None = None
    config_flags: int | None = None
    gyro_fw_version: int | None = None
    extra: bytes = b""


_STR = "str"
# Every CONFIG field after the three leading strings, in wire order: (field name, struct format or _STR).
_CONFIG_LAYOUT: tuple[tuple[str, str], ...] = (
    ("four_mots", "<B"), ("rotvel_top", "<H"), ("transvel_top", "<H"), ("rotaccel_top", "<H"),
    ("transaccel_top", "<H"), ("pwm_max", "<H"), ("name", _STR),
    ("sip_cycle", "<B"), ("host_baud", "<B"), ("aux_baud", "<B"), ("gripper", "<H"), ("front_sonar", "<H"),
    ("rear_sonar", "<B"), ("low_battery", "<H"), ("revcount", "<H"), ("watchdog", "<H"),
    ("normal_mpacs", "<B"), ("stall_val", "<H"), ("stall_count", "<H"), ("joy_vel", "<H"),
    ("joy_rotvel", "<H"), ("rotvel_max", "<H"), ("transvel_max", "<H"), ("rot_accel", "<H"),
    ("rot_decel", "<H"), ("rot_kp", "<H"), ("rot_kv", "<H"), ("rot_ki", "<H"), ("trans_accel", "<H"),
    ("trans_decel", "<H"), ("trans_kp", "<H"), ("trans_kv", "<H"), ("trans_ki", "<H"),
    ("front_bumps", "<B"), ("rear_bumps", "<B"), ("has_charger", "<B"), ("sonar_cycle", "<B"),
    ("reset_baud", "<B"), ("gyro_type", "<B"), ("drift_factor", "<h"), ("aux2_baud", "<B"),
    ("aux3_baud", "<B"), ("ticks_mm", "<H"), ("shutdown_voltage", "<H"), ("firmware_version", _STR),
    ("gyro_cw", "<H"), ("gyro_ccw", "<H"), ("kinematics_delay", "<B"), ("latvel_top", "<H"),
    ("lataccel_top", "<H"), ("latvel_max", "<H"), ("lat_accel", "<H"), ("lat_decel", "<H"),
    ("charge_threshold", "<H"), ("pdb_port", "<B"), ("gyro_rate_limit", "<H"),
    ("high_temperature_shutdown", "<b"), ("power_bits", "<H"), ("battery_type", "<B"),
    ("state_of_charge_low", "<H"), ("state_of_charge_shutdown", "<H"), ("bootloader_version", _STR),
    ("config_flags", "<I"), ("gyro_fw_version", "<h"),
)
_CONFIG_REQUIRED = 1 + [name for name, _ in _CONFIG_LAYOUT].index("watchdog")


def decode_config(payload: bytes) -> ConfigPacket:
    """Decode a CONFIG payload. Raises DecodeError when it ends before the watchdog field.

    Fields after the watchdog are read while whole fields remain; the rest stay None.
    """
    (rtype, sub, serial), off = _split_strings(payload, 3, "CONFIG packet")
    vals: dict[str, object] = {}
    for k, (name, fmt) in enumerate(_CONFIG_LAYOUT):
        if fmt == _STR:
            end = payload.find(b"\x00", off)
            if end < 0:
                if k < _CONFIG_REQUIRED:
                    raise DecodeError(f"CONFIG packet: string field {name} is not NUL-terminated")
                break
            vals[name] = payload[off:end].decode("latin-1")
            off = end + 1
            continue
        size = struct.calcsize(fmt)
        if len(payload) - off < size:
            if k < _CONFIG_REQUIRED:
                raise DecodeError(f"CONFIG packet ends before field {name} ({len(payload)} bytes)")
            break
        (vals[name],) = struct.unpack_from(fmt, payload, off)
        off += size
    return ConfigPacket(rtype, sub, serial, extra=bytes(payload[off:]), **vals)  # type: ignore[arg-type]


def encode_config(cfg: ConfigPacket) -> bytes:
    """Framed CONFIG packet (emulator side): every field up to the last one that is not None."""
    p = bytearray()
    for s in (cfg.robot_type, cfg.subtype, cfg.serial):
        p += s.encode("latin-1") + b"\x00"
    values = [getattr(cfg, name) for name, _ in _CONFIG_LAYOUT]
    last = max((k for k, v in enumerate(values) if v is not None), default=-1)
    for (name, fmt), value in zip(_CONFIG_LAYOUT[: last + 1], values):
        if fmt == _STR:
            p += (value or "").encode("latin-1") + b"\x00"
        else:
            p += struct.pack(fmt, value or 0)
    p += cfg.extra
    return build_packet(PacketType.CONFIG, bytes(p))


@dataclass(frozen=True)
class EncoderPacket:
    """ENCODER packet (0x90): raw left and right encoder counts."""

    left: int
    right: int


def decode_encoder(payload: bytes) -> EncoderPacket:
    if len(payload) < 8:
        raise DecodeError(f"ENCODER packet too short: {len(payload)} bytes < 8")
    return EncoderPacket(*struct.unpack_from("<ii", payload, 0))


def encode_encoder(enc: EncoderPacket) -> bytes:
    return build_packet(PacketType.ENCODER, struct.pack("<ii", enc.left, enc.right))


@dataclass(frozen=True)
class UnknownPacket:
    """A valid packet whose ID this driver does not interpret (skipped, counted)."""

    pid: int
    payload: bytes = field(repr=False)


ServerMessage = StandardSIP | ConfigPacket | EncoderPacket | UnknownPacket


def decode_packet(packet: Packet) -> ServerMessage:
    """Typed view of a server packet received while the connection is open.

    SIPs, CONFIG and ENCODER are decoded; any other ID gives :class:`UnknownPacket`. Raises DecodeError
    (only) for a known ID whose payload is malformed.
    """
    if packet.pid in SIP_IDS:
        return decode_sip(packet.pid, packet.payload)
    if packet.pid == PacketType.CONFIG:
        return decode_config(packet.payload)
    if packet.pid == PacketType.ENCODER:
        return decode_encoder(packet.payload)
    return UnknownPacket(packet.pid, packet.payload)


SIP_TAIL_FIELDS = tuple(name for name, _ in _SIP_TAIL)
assert set(SIP_TAIL_FIELDS) <= {f.name for f in fields(StandardSIP)}
assert {name for name, _ in _CONFIG_LAYOUT} <= {f.name for f in fields(ConfigPacket)}
