"""Hardware-in-the-loop: the real HokuyoClient against the emulator over a pty and loopback TCP.

For every fault mode the client must deliver exactly the intact scans the emulator sent (same stamps, same
order, none lost, none extra) and count every bad one.
"""

import asyncio
import math

import numpy as np
import pytest

from drivers.capture import CaptureRecorder
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.emulator import Faults, HokuyoEmulator, canned_scan_source, ranges_to_codes, room_scan_source
from tests.helpers import eventually

pytestmark = pytest.mark.timeout(60)

SCALE = 4.0  # emulated seconds per real second


async def serve(link, **kw):
    kw.setdefault("time_scale", SCALE)
    emu = HokuyoEmulator(kw.pop("source", None) or room_scan_source(), **kw)
    url = await (emu.serve_tcp() if link == "tcp" else emu.serve_pty())
    return emu, url


async def take(client, n):
    out = []
    async for scan in client.scans():
        out.append(scan)
        if len(out) >= n:
            break
    return out


def raw_stamps(scans):
    return [int(round(s.sensor_stamp * 1000)) % (1 << 24) for s in scans]


FAULT_MODES = {
    "none": Faults(),
    "checksum": Faults(checksum_every=5, seed=1),
    "drop": Faults(drop_every=4, seed=2),
    "garbage": Faults(garbage_every=3, seed=3),
    "coalesce": Faults(coalesce_every=2),
    "status": Faults(status_every=6),
    "all_per_scan": Faults(status_every=7, checksum_every=11, drop_every=13, garbage_every=5, coalesce_every=3,
                           seed=4),
    "clock_jump": Faults(clock_jump_at=40, clock_jump_s=-100.0),
}


@pytest.mark.parametrize("link", ["tcp", "pty"])
@pytest.mark.parametrize("mode", list(FAULT_MODES))
async def test_every_good_scan_arrives_and_every_bad_one_is_counted(link, mode):
    faults = FAULT_MODES[mode]
    emu, url = await serve(link, faults=faults, clock_start_ms=(1 << 24) - 1000)  # wraps during the test
    client = await HokuyoClient.connect(url)
    scans = await take(client, 80)
    await client.close()
    es, cs = emu.stats, client.stats
    assert raw_stamps(scans) == list(es.good_stamps)[:80]
    assert cs.corrupted == es.scans_corrupted
    assert cs.error_statuses == es.error_statuses
    assert cs.garbage_bytes == es.garbage_bytes
    assert cs.unexpected == 0 and cs.reconnects == 0 and cs.dropped == 0
    assert cs.clock_jumps == es.clock_jumps
    assert emu.state == "idle"  # QT confirmed
    s = scans[-1]
    assert s.ranges.shape == (1081,) and s.intensities.shape == (1081,) and s.geometry.n_beams == 1081
    assert [x.seq for x in scans] == list(range(1, 81))
    if mode == "clock_jump":  # the sensor clock went back 100 s; host stamps do not follow it
        assert scans[45].sensor_stamp < scans[35].sensor_stamp - 90
        stamps = np.array([x.stamp for x in scans[30:]])
        assert np.abs(np.diff(stamps)).max() < 1.0
    await emu.close()


@pytest.mark.parametrize("link", ["tcp", "pty"])
@pytest.mark.parametrize("event", ["disconnect", "reboot"])
async def test_reconnects_after_cable_pull_and_reboot_with_the_same_stream(link, event):
    faults = Faults(disconnect_at=25) if event == "disconnect" else Faults(reboot_at=25)
    emu, url = await serve(link, faults=faults, boot_time=1.0, clock_start_ms=5_000_000)
    rec = CaptureRecorder("hokuyo")
    client = await HokuyoClient.connect(url, HokuyoSettings(cluster=2, start_step=100, end_step=980), taps=[rec])
    scans = await take(client, 60)
    await client.close()
    assert client.stats.reconnects == 1
    assert raw_stamps(scans) == list(emu.stats.good_stamps)[:60]
    after = scans[-1]
    assert after.intensities is not None and after.ranges.shape == (441,)  # same steps and cluster
    # the taps saw both connections: two stream starts in the recorded host -> device bytes
    assert rec.capture.tx_bytes().count(b"ME0100098002000\n") == 2
    if event == "reboot":
        assert scans[30].sensor_stamp < scans[20].sensor_stamp  # the sensor clock restarted
    await emu.close()


async def test_watchdog_notices_a_silent_sensor():
    emu, url = await serve("tcp", faults=Faults(silence_at=20, silence_s=4.0))
    client = await HokuyoClient.connect(url, HokuyoSettings(watchdog=0.3, timeout=0.3))
    scans = await take(client, 50)
    await client.close()
    assert client.stats.watchdog_trips >= 1 and client.stats.reconnects >= 1
    assert raw_stamps(scans) == list(emu.stats.good_stamps)[:50]
    await emu.close()


async def test_close_confirms_the_stop_when_qt_is_ignored():
    emu, url = await serve("pty", faults=Faults(ignore_qt=1))
    client = await HokuyoClient.connect(url)  # the first QT (at open) is ignored too
    await take(client, 5)
    await client.close()
    assert emu.stats.qt_ignored == 1 and emu.state == "idle"
    await emu.close()


async def test_cancelled_consumer_still_stops_the_sensor():
    emu, url = await serve("tcp")

    async def consumer():
        async with HokuyoClient.connect(url) as client:
            async for _ in client.scans():
                pass

    task = asyncio.create_task(consumer())
    await eventually(lambda: emu.state == "streaming", what="the emulator streaming")
    await asyncio.sleep(0.1)
    task.cancel()  # what Ctrl-C does to the main task
    with pytest.raises(asyncio.CancelledError):
        await task
    assert emu.state == "idle"
    await emu.close()


async def test_slow_consumer_drops_oldest_and_counts_them():
    emu, url = await serve("tcp")
    client = await HokuyoClient.connect(url, HokuyoSettings(queue_size=4))
    await eventually(lambda: client.stats.received >= 30, what="30 scans received")
    scans = await take(client, 4)
    await client.close()
    assert client.stats.dropped >= 20
    assert client.stats.received - client.stats.dropped >= 4
    assert np.all(np.diff([s.seq for s in scans]) == 1)  # the newest ones, in order
    await emu.close()


async def test_values_geometry_and_multi_echo_match_the_source():
    rng = np.random.default_rng(5)
    r = np.column_stack([rng.uniform(0.05, 40.0, 1081), np.full(1081, np.nan)])
    r[::3, 1] = r[::3, 0] + 2.0  # a second echo on every third beam
    r[7, 0], r[8, 0] = np.inf, np.nan
    inten = np.column_stack([rng.uniform(0, 9000, 1081), np.full(1081, 500.0)])
    emu, url = await serve("tcp", source=canned_scan_source(r[None], inten[None]))
    async with HokuyoClient.connect(url, HokuyoSettings(multi_echo=True)) as client:
        (scan,) = await take(client, 1)
    g = scan.geometry
    assert g.n_beams == 1081 and g.angle_min == pytest.approx(-3 * math.pi / 4)
    assert g.angle_increment == pytest.approx(math.pi / 720) and g.scan_time == pytest.approx(0.025)
    assert g.range_min == pytest.approx(0.023) and g.range_max == pytest.approx(60.0)
    want = ranges_to_codes(r[:, 0]) / 1000.0
    ok = np.isfinite(r[:, 0]) & (r[:, 0] >= 0.023)
    assert np.allclose(scan.ranges[ok], want[ok])
    assert np.isinf(scan.ranges[7]) and np.isnan(scan.ranges[8])
    assert np.array_equal(scan.intensities, np.rint(inten[:, 0]))
    assert scan.echoes.shape == (1081, 2)
    assert np.allclose(scan.echoes[::3, 0], np.rint(r[::3, 1] * 1000) / 1000)
    assert np.isnan(scan.echoes[1::3, 0]).all() and np.isnan(scan.echoes[:, 1]).all()
    assert np.allclose(scan.echo_intensities[::3, 0], 500.0)
    await emu.close()


async def test_bad_step_range_is_a_value_error():
    emu, url = await serve("tcp")
    with pytest.raises(ValueError, match="outside"):
        await HokuyoClient.connect(url, HokuyoSettings(start_step=0, end_step=2000))
    with pytest.raises(ValueError):
        HokuyoSettings(skip=12)
    await emu.close()


async def test_without_reconnect_a_lost_link_ends_the_scans_with_the_error():
    from drivers.errors import TransportClosed

    emu, url = await serve("tcp", faults=Faults(disconnect_at=10))
    client = await HokuyoClient.connect(url, HokuyoSettings(reconnect=False))
    with pytest.raises(TransportClosed):
        await take(client, 1000)
    await client.close()
    await emu.close()


async def test_without_reconnect_a_silent_sensor_raises_sensor_silent():
    from drivers.hokuyo.errors import SensorSilent

    emu, url = await serve("tcp", faults=Faults(silence_at=10, silence_s=8.0))
    client = await HokuyoClient.connect(url, HokuyoSettings(reconnect=False, watchdog=0.3))
    with pytest.raises(SensorSilent, match="watchdog"):
        await take(client, 1000)
    await client.close()
    await emu.close()
