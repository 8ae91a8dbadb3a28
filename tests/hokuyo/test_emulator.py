"""The UTM-30LX-EW emulator, spoken to with raw SCIP bytes over loopback TCP and a pty."""

import asyncio

import numpy as np
import pytest

from drivers.hokuyo.emulator import (
    Faults,
    HokuyoEmulator,
    canned_scan_source,
    ranges_to_codes,
    room_scan_source,
)
from drivers.hokuyo.scip import InfoReply, ScanReply, ScipParser, TimeReply
from drivers.transport import open_transport
from tests.hokuyo.vectors import PP_REPLY
from tests.helpers import eventually

pytestmark = pytest.mark.timeout(30)


class Raw:
    """A bare SCIP conversation: write lines, collect parsed replies."""

    def __init__(self, transport):
        self.t = transport
        self.parser = ScipParser()
        self.rx = bytearray()
        self.items = []

    async def send(self, line: bytes, n: int = 1, timeout: float = 3.0):
        start = len(self.items)
        await self.t.write(line)
        while len(self.items) < start + n:
            data = await asyncio.wait_for(self.t.read(), timeout)
            self.rx += data
            self.items += self.parser.feed(data)
        return self.items[start:start + n] if n > 1 else self.items[start]


@pytest.fixture(params=["tcp", "pty"])
async def raw(request):
    emu = HokuyoEmulator(room_scan_source(), time_scale=4.0)
    url = await (emu.serve_tcp() if request.param == "tcp" else emu.serve_pty())
    t = await open_transport(url)
    yield Raw(t), emu
    await t.close()
    await emu.close()


async def test_pp_reply_is_byte_identical_to_a_real_unit(raw):
    r, _ = raw
    reply = await r.send(b"PP\n")
    assert isinstance(reply, InfoReply)
    assert bytes(r.rx) == PP_REPLY


async def test_state_machine_and_status_codes(raw):
    r, emu = raw
    assert (await r.send(b"GD0000108001\n")).status == "10"  # laser off
    assert (await r.send(b"BM\n")).status == "00" and emu.state == "laser_on"
    assert (await r.send(b"BM\n")).status == "02"
    scan = await r.send(b"GE0000108001\n")
    assert isinstance(scan, ScanReply) and scan.status == "00" and scan.n_steps == 1081
    assert (await r.send(b"QT\n")).status == "00" and emu.state == "idle"
    assert (await r.send(b"TM1\n")).status == "04"
    assert (await r.send(b"TM2\n")).status == "03"
    assert (await r.send(b"TM0\n")).status == "00" and emu.state == "time_sync"
    assert (await r.send(b"TM0\n")).status == "02"
    t1 = await r.send(b"TM1\n")
    assert isinstance(t1, TimeReply) and 0 <= t1.time_ms < 1 << 24
    assert (await r.send(b"MD0000108001000\n")).status == "10"  # no measuring in time-sync mode
    assert (await r.send(b"TM2\n")).status == "00" and emu.state == "idle"
    assert (await r.send(b"%ST\n")).status == "0E"
    assert (await r.send(b"XY\n")).status == "0E"
    assert (await r.send(b"RT\n")).status == "0F"
    assert (await r.send(b"VV;" + b"a" * 17 + b"\n")).status == "0G"
    assert (await r.send(b"MD0000200001000\n")).status == "04"  # end step beyond AMAX
    assert (await r.send(b"MD0500010001000\n")).status == "05"  # end < start
    assert (await r.send(b"MD00001080\n")).status == "0H"
    assert (await r.send(b"RB\n")).status == "01"  # a reboot needs a second RB within 1 s


async def test_accepts_cr_lf_and_crlf_and_echoes_the_string(raw):
    r, _ = raw
    for term in (b"\n", b"\r", b"\r\n"):
        reply = await r.send(b"VV;id" + term)
        assert reply.echo.string == "id" and reply.fields["PROT"] == "SCIP 2.0"
    assert b"\r" not in r.rx  # the sensor sends LF only


async def test_finite_stream_counts_down_and_skip_spaces_the_stamps(raw):
    r, emu = raw
    ack, *scans = await r.send(b"ME0000108001203\n", n=4)  # skip 2 (send every third), 3 scans
    assert ack.status == "00"
    assert [s.remaining for s in scans] == [2, 1, 0]
    assert [s.echo.raw[-2:] for s in scans] == [b"02", b"01", b"00"]
    assert np.diff([s.timestamp_ms for s in scans]).tolist() == [75, 75]  # 3 revolutions of 25 ms
    assert emu.state == "laser_on"


async def test_ii_reports_laser_and_encoded_time(raw):
    r, _ = raw
    ii = await r.send(b"II\n")
    assert ii.fields["LASR"] == "OFF" and len(ii.fields["TIME"]) == 4 and ii.fields["MODL"] == "UTM-30LX-EW"


def test_ranges_to_error_codes():
    r = np.array([np.nan, np.inf, 0.01, 0.023, 1.2344, 60.0, 61.0])
    assert ranges_to_codes(r).tolist() == [3, 1, 2, 23, 1234, 60000, 1]


async def test_clusters_report_the_minimum_valid_reading():
    ranges = np.full(1081, 5.0)
    ranges[10] = 1.0
    ranges[11] = np.nan
    ranges[12:15] = np.inf
    inten = np.arange(1081.0)
    emu = HokuyoEmulator(canned_scan_source(ranges, inten), time_scale=4.0)
    url = await emu.serve_tcp()
    t = await open_transport(url)
    r = Raw(t)
    await r.send(b"BM\n")
    scan = await r.send(b"GE0009001503\n")  # steps 9..15, clusters of 3: [9,10,11] [12,13,14] [15]
    assert scan.distances.tolist() == [1000, 1, 5000]
    assert scan.intensities.tolist() == [10, 12, 15]
    await t.close()
    await emu.close()


async def test_clock_starts_where_told_and_wraps():
    emu = HokuyoEmulator(room_scan_source(), time_scale=4.0, clock_start_ms=(1 << 24) - 60)
    url = await emu.serve_tcp()
    t = await open_transport(url)
    r = Raw(t)
    ack, *scans = await r.send(b"MD0000108000010\n", n=11)
    stamps = [s.timestamp_ms for s in scans]
    assert stamps[0] > (1 << 24) - 100 and stamps[-1] < 500  # wrapped to small values
    await t.close()
    await emu.close()


async def test_reboot_drops_the_link_and_restarts_the_clock():
    emu = HokuyoEmulator(room_scan_source(), time_scale=4.0, boot_time=1.0, clock_start_ms=5_000_000)
    url = await emu.serve_tcp()
    t = await open_transport(url)
    r = Raw(t)
    assert (await r.send(b"RB\n")).status == "01"
    assert (await r.send(b"RB\n")).status == "00"
    from drivers.errors import TransportClosed

    with pytest.raises(TransportClosed):
        while True:
            await asyncio.wait_for(t.read(), 3)
    await t.close()
    await eventually(lambda: emu.state != "booting", what="the emulator's reboot to end")
    t = await open_transport(url)
    r = Raw(t)
    assert (await r.send(b"TM0\n")).status == "0M"  # field units refuse TM0 for a while after boot
    ii = await r.send(b"II\n")
    assert emu.stats.reboots == 1 and emu.clock_ms() < 100_000
    assert ii.fields["LASR"] == "OFF"
    await t.close()
    await emu.close()


def test_fault_spec_parsing():
    f = Faults.parse("checksum_every=50, drop_every=70,clock_jump_s=-3.5,reboot_at=9")
    assert (f.checksum_every, f.drop_every, f.clock_jump_s, f.reboot_at) == (50, 70, -3.5, 9)
    with pytest.raises(ValueError, match="bad fault"):
        Faults.parse("checksums=3")


async def test_two_character_commands_saturate_at_4095_mm(raw):
    r, _ = raw
    ack, scan = await r.send(b"MS0000108001001\n", n=2)  # the room is wider than 4.095 m
    assert scan.distances.max() == 4095 and scan.n_steps == 1081
