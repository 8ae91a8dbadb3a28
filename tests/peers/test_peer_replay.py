"""Peer fixtures, replayed: what ARIA and urg_library sent to our emulators, sent again to our emulators.

The captures were recorded from the real third-party programs (tests/fakes/captures/README.md); here the
peer's side (``tx``) is played back at its recorded times and the emulator must answer as it did when the
peer accepted it: the same handshake and CONFIG bytes, the same commands, the same drive. ARIA's sessions
are fed to the controller in emulated time (deterministic, no link); one goes over a pty with the baud
switch; urg_library's go over a pty in real time. The device side
the peers accepted (``rx``) is also fed to our own decoders.
"""

from __future__ import annotations

import asyncio
import json
import math
import time

import pytest

from drivers.capture import Capture
from drivers.capture import CaptureRecorder
from drivers.hokuyo.emulator import HokuyoEmulator, room_scan_source
from drivers.hokuyo.scip import InfoReply, ScanReply, ScipParser
from drivers.pioneer.emulator import HOSTBAUD_SPEEDS, PioneerEmulator
from drivers.pioneer.packets import SIP_IDS, Cmd, PacketParser, parse_int_arg
from drivers.pioneer.sip import decode_config, decode_sip
from drivers.transport import open_transport
from tests.peers.harness import ARIA_SESSIONS, CAPTURE_DIR, URG_SESSIONS

pytestmark = pytest.mark.timeout(120)
SCALE = 10.0  # the pty replay runs 10x faster than recorded (the emulator at the same scale)


def load(name: str) -> tuple[Capture, dict]:
    cap = Capture.load(CAPTURE_DIR / f"peer-{name}.jsonl")
    meta = json.loads(cap.note)
    assert meta["kind"] == "peer"
    return cap, meta


def packets(data: bytes):
    parser = PacketParser(inter_byte_timeout=None)
    out = parser.feed(data)
    assert parser.stats.bad_checksum == 0 and parser.stats.bad_length == 0
    return out


async def replay_host_side(cap: Capture, emu, url: str, scale: float, *, baud_switch: bool = False) -> bytes:
    """Send the capture's tx chunks at their recorded times / scale; return what the host received."""
    t = await open_transport(url)
    got = bytearray()

    async def reader():
        while True:
            got.extend(await t.read())

    rtask = asyncio.ensure_future(reader())
    t0 = time.monotonic()
    try:
        for chunk in cap.chunks:
            if chunk.direction != "tx":
                continue
            await asyncio.sleep(max(0.0, t0 + chunk.t / scale - time.monotonic()))
            await t.write(chunk.data)
            hb = [p for p in packets(chunk.data) if p.pid == Cmd.HOSTBAUD] if baud_switch else []
            if hb:  # as the peer did: its own end follows once the controller has switched
                speed = HOSTBAUD_SPEEDS[parse_int_arg(hb[-1].payload)]
                end = time.monotonic() + 2.0
                while emu.line_baud != speed and time.monotonic() < end:
                    await asyncio.sleep(0.001)
                await t.set_baudrate(speed)
        await asyncio.sleep(0.3)
    finally:
        rtask.cancel()
        await t.close()
    return bytes(got)


def aria_commands(cap: Capture) -> list[tuple[int, int | None]]:
    """What ARIA sent after OPEN, as the controller logs it (SYNC0-2 aside; OPEN shares ID 1 with SYNC1)."""
    sent = [(p.pid, parse_int_arg(p.payload)) for p in packets(cap.tx_bytes())]
    synced = next(k for k, (pid, _) in enumerate(sent) if pid == 2)
    opened = next(k for k, (pid, _) in enumerate(sent) if k > synced and pid == Cmd.OPEN)
    return [(pid, arg if pid != Cmd.OPEN else None) for pid, arg in sent[opened:]]


def replies(data: bytes) -> list[tuple[int, bytes]]:
    """Every packet but the SIPs: SYNC echoes, the SYNC2 identity, CONFIG."""
    return [(p.pid, p.payload) for p in packets(data) if p.pid not in SIP_IDS]


@pytest.mark.parametrize("session", ARIA_SESSIONS, ids=lambda s: s.name)
def test_aria_session_replays_against_the_emulator(session):
    """ARIA's bytes at their recorded times, fed to the controller in emulated time (deterministic)."""
    cap, meta = load(session.name)
    emu = PioneerEmulator(seed=0)
    emu.go_offline()
    rec = CaptureRecorder("pioneer")
    emu.taps.append(rec)
    for chunk in cap.chunks:
        if chunk.direction == "tx":
            emu.advance(chunk.t)
            emu.receive(chunk.data)
    emu.advance(cap.chunks[-1].t + 1.0)
    assert [(c.cmd, c.arg) for c in emu.received] == aria_commands(cap)
    assert emu.stats.bad_packets_received == 0
    # the answers ARIA accepted, byte for byte
    assert replies(rec.capture.rx_bytes()) == replies(cap.rx_bytes())
    # the drive: the distance the program commands, and the pose of the recorded run (the controller's
    # cycle phase against ARIA's commands differs from the live run by up to one 100 ms cycle)
    want = meta["result"]
    assert emu.robot.distance == pytest.approx(session.distance, rel=0.05, abs=0.02)
    assert emu.robot.distance == pytest.approx(want["distance_m"], abs=0.05)
    x, y, th = emu.robot.true_pose
    assert math.hypot(x - want["x_m"], y - want["y_m"]) < 0.1
    assert abs(math.degrees(th) - want["heading_deg"]) < 5.0
    if session.heading is not None:
        assert abs(math.degrees(th) - session.heading) < 3.0


async def test_aria_connect_replays_over_a_pty_with_the_baud_switch():
    """The link itself: ARIA's connect session over a pty, its end following HOSTBAUD to 38400."""
    cap, _ = load("aria-simpleConnect")
    emu = PioneerEmulator(seed=0, time_scale=SCALE)
    url = await emu.serve_pty()
    rec = CaptureRecorder("pioneer")
    emu.taps.append(rec)
    try:
        await replay_host_side(cap, emu, url, SCALE, baud_switch=True)
    finally:
        await emu.close()
    assert [(c.cmd, c.arg) for c in emu.received] == aria_commands(cap)
    assert emu.hostbaud == 2 and emu.stats.bad_packets_received == 0
    assert emu.stats.baud_mismatch_bytes < 200  # at most the SIPs in flight while both ends switch speed
    assert replies(rec.capture.rx_bytes()) == replies(cap.rx_bytes())


@pytest.mark.parametrize("session", ARIA_SESSIONS, ids=lambda s: s.name)
def test_the_robot_side_aria_accepted_decodes_with_our_codec(session):
    cap, _ = load(session.name)
    pk = packets(cap.rx_bytes())
    cfg = decode_config(next(p for p in pk if p.pid == 0x20).payload)
    assert cfg.transvel_max == 1500 and cfg.rotvel_max == 300 and cfg.bootloader_version is not None
    sips = [decode_sip(p.pid, p.payload) for p in pk if p.pid in SIP_IDS]
    assert len(sips) > 20 and all(s.sonar_arrays or not s.sonar for s in sips)


def scip_replies(data: bytes) -> list:
    out = ScipParser().feed(data)
    assert not [r for r in out if isinstance(r, Exception)]
    return out


@pytest.mark.parametrize("session", URG_SESSIONS, ids=lambda s: s.name)
async def test_urg_session_replays_against_the_emulator(session):
    cap, meta = load(session.name)
    emu = HokuyoEmulator(room_scan_source())
    url = await emu.serve_pty()
    rec = CaptureRecorder("hokuyo")
    emu.taps.append(rec)
    try:
        await replay_host_side(cap, emu, url, 1.0)
    finally:
        await emu.close()
    want, got = scip_replies(cap.rx_bytes()), scip_replies(rec.capture.rx_bytes())
    # the replies to single commands, in order; PP and VV byte for byte (the identity urg_library read)
    singles = [(r.echo.raw, r.status) for r in want if not isinstance(r, ScanReply)]
    assert [(r.echo.raw, r.status) for r in got if not isinstance(r, ScanReply)] == singles
    info = [r for r in want if isinstance(r, InfoReply) and r.command in ("PP", "VV")]
    assert [r for r in got if isinstance(r, InfoReply) and r.command in ("PP", "VV")] == info
    # the stream: the same echo, full scans; as many as the peer took, give or take the one in flight when
    # its QT went out (the emulator streams in real time)
    want_scans, got_scans = ([r for r in rs if isinstance(r, ScanReply)] for rs in (want, got))
    assert abs(len(got_scans) - len(want_scans)) <= 2
    for a in got_scans:
        b = want_scans[0]
        assert (a.echo.raw, a.distances.shape, a.intensities is None) == (b.echo.raw, (1081,), b.intensities is None)
