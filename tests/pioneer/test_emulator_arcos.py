"""The emulated controller behaves as ARCOS does where the reference client (ARIA) depends on it: the full
CONFIG packet and its current velocity limits, the serial speed switch, and sonar from OPEN."""

from __future__ import annotations

import asyncio

import pytest

from drivers.pioneer.packets import SYNC0, SYNC1, SYNC2, Cmd, PacketParser, build_packet, command
from drivers.pioneer.sip import decode_config, decode_sip
from drivers.transport import open_transport
from tests.helpers import eventually

pytestmark = pytest.mark.timeout(60)


async def open_session(emu, url):
    t = await open_transport(url)
    for pid in (SYNC0, SYNC1, SYNC2):
        await t.write(build_packet(pid))
        await eventually(lambda: emu._session >= pid + 1, what=f"SYNC{pid} accepted")
    await t.write(command(Cmd.OPEN))
    await eventually(lambda: emu.is_open, what="OPEN")
    return t


async def read_packets(t, parser, pred, what):
    got = []
    async def loop():
        while not any(pred(p) for p in got):
            got.extend(parser.feed(await t.read()))
    await asyncio.wait_for(loop(), 10.0)
    return got


def sips(packets):
    return [decode_sip(p.pid, p.payload) for p in packets if p.pid in (0x32, 0x33)]


async def test_config_has_current_limits_and_vel_is_capped_by_them(emulator_factory):
    emu, url = await emulator_factory()
    t = await open_session(emu, url)
    try:
        await t.write(command(Cmd.CONFIG))
        pkts = await read_packets(t, PacketParser(), lambda p: p.pid == 0x20, "CONFIG")
        cfg = decode_config(next(p for p in pkts if p.pid == 0x20).payload)
        assert 0 < cfg.transvel_max < cfg.transvel_top and 0 < cfg.rotvel_max < cfg.rotvel_top
        assert cfg.trans_accel > 0 and cfg.rot_accel > 0 and cfg.reset_baud == 2
        assert cfg.bootloader_version is not None  # the packet runs to its last field
        await t.write(command(Cmd.ENABLE, 1) + command(Cmd.VEL, 2000))
        await eventually(lambda: emu.robot.velocity[0] > 0.1, what="moving")
        await t.write(command(Cmd.PULSE))
        assert emu._max_v == pytest.approx(cfg.transvel_max / 1000)
        await t.write(command(Cmd.SETV, 1800) + command(Cmd.VEL, 2000))
        await eventually(lambda: emu._max_v == pytest.approx(1.8), what="SETV raises the limit")
    finally:
        await t.write(command(Cmd.ENABLE, 0) + command(Cmd.CLOSE))
        await t.close()


async def test_sonar_fires_from_open_and_follows_the_sonar_command(emulator_factory):
    emu, url = await emulator_factory()
    t = await open_session(emu, url)
    parser = PacketParser()
    try:
        first = sips(await read_packets(t, parser, lambda p: p.pid in (0x32, 0x33), "SIP"))
        assert first[0].sonar and first[0].sonar_arrays == 0b11  # no SONAR command needed
        await t.write(command(Cmd.SONAR, 0))
        await eventually(lambda: not emu.sonar_enabled, what="SONAR 0")
        await t.read()
        parser = PacketParser()
        off = sips(await read_packets(t, parser, lambda p: p.pid in (0x32, 0x33), "SIP"))
        assert not off[-1].sonar and off[-1].sonar_arrays == 0
        await t.write(command(Cmd.SONAR, 0b011))  # on, front array only
        await eventually(lambda: emu.sonar_enabled, what="SONAR front")
        await t.read()
        parser = PacketParser()
        n = 0
        while n < 6:
            for s in sips(parser.feed(await t.read())):
                n += 1
                assert s.sonar_arrays == 0b01 and s.sonar and all(i < 8 for i, _ in s.sonar)
    finally:
        await t.write(command(Cmd.CLOSE))
        await t.close()


async def test_hostbaud_switches_the_line_and_close_returns_to_9600(emulator_factory):
    emu, url = await emulator_factory()
    t = await open_session(emu, url)
    try:
        await t.set_baudrate(38400)  # the host changes speed on its own: the line is garbage both ways
        lost = emu.stats.baud_mismatch_bytes
        await eventually(lambda: emu.stats.baud_mismatch_bytes > lost + 100, what="SIPs lost at the wrong speed")
        await t.set_baudrate(9600)
        await t.write(command(Cmd.HOSTBAUD, 2))
        await eventually(lambda: emu.line_baud == 38400, what="HOSTBAUD 2")
        await t.set_baudrate(38400)
        await t.read()
        got = sips(await read_packets(t, PacketParser(), lambda p: p.pid in (0x32, 0x33), "SIP at 38400"))
        assert got
        await t.write(command(Cmd.CLOSE))
        await eventually(lambda: not emu.is_open, what="CLOSE")
        assert emu.line_baud == 9600
    finally:
        await t.close()
