"""One receive path: the bytes a live client read, fed again to the same session by the raw replay, give
the same scans and odometry (multi-echo, faults and reconnections included)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from drivers.capture import Capture, CaptureRecorder
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.emulator import Faults, HokuyoEmulator, room_scan_source
from drivers.pioneer.client import PioneerClient
from runtime.raw_replay import HokuyoReplay, PioneerReplay
from tests.pioneer.conftest import SCALE, emulator_factory, fast_settings  # noqa: F401 (fixture)
from tests.pioneer.test_replay import offline
from tests.pioneer.make_captures import SESSIONS

pytestmark = pytest.mark.timeout(60)


def replay(capture: Capture, device) -> list:
    out = []
    for c in capture.chunks:
        if c.direction == "tx":
            device.tx(c.t, c.data)
        else:
            out.extend(device.rx(c.t, c.data))
    return out


def same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b, equal_nan=True))


async def test_raw_replay_of_a_multi_echo_session_gives_the_live_scans_echoes_included():
    faults = Faults(checksum_every=7, garbage_every=5, coalesce_every=3, disconnect_at=25, seed=1)
    emu = HokuyoEmulator(room_scan_source(), faults=faults, time_scale=4.0)
    url = await emu.serve_tcp()
    rec = CaptureRecorder("hokuyo")
    live = []
    async with HokuyoClient.connect(url, HokuyoSettings(multi_echo=True, cluster=2), taps=[rec]) as laser:
        async for scan in laser.scans():
            live.append(scan)  # a cable pull at the 25th scan: the client reconnects on a new link
            if len(live) >= 50:
                break
        stats = laser.stats
    await emu.close()
    assert stats.reconnects == 1 and stats.corrupted > 0 and stats.garbage_bytes > 0

    rep = HokuyoReplay()
    replayed = replay(rec.capture, rep)[:len(live)]
    assert rep.session.links == 2 + 1  # the session's own first link, then the reconnection and the close
    assert [s.seq for s in replayed] == [s.seq for s in live]
    assert [s.sensor_stamp for s in replayed] == [s.sensor_stamp for s in live]
    for r, s in zip(replayed, live):
        assert s.echoes is not None and same(r.echoes, s.echoes) and same(r.echo_intensities, s.echo_intensities)
        assert same(r.ranges, s.ranges) and same(r.intensities, s.intensities) and r.geometry == s.geometry
    # host stamps: the capture's clock starts at its first chunk; relative stamps agree
    d_live = np.diff([s.stamp for s in live])
    d_rep = np.diff([s.stamp for s in replayed])
    assert np.allclose(d_rep, d_live, atol=1e-4)
    assert rep.session.stats.corrupted >= stats.corrupted  # the replay also sees what came after the close


async def test_raw_replay_of_a_driving_session_gives_the_live_odometry(emulator_factory):
    emu, url = await emulator_factory()
    rec = CaptureRecorder("pioneer")
    live = []
    async with PioneerClient.connect(url, fast_settings(), taps=[rec], enable_motors=True) as base:
        base.odometry_callbacks.append(live.append)
        for _ in range(30):
            await base.set_velocity(0.3, math.radians(20))
            await asyncio.sleep(0.02)
        emu.link_loss(0.5)
        for _ in range(200):
            if base.stats.reconnects:
                break
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
    assert base.stats.reconnects == 1 and len(live) > 10
    assert base.stats.still_open_recoveries == 1  # the robot was still open at the reconnection: its SIPs
    # before the CLOSE belong to the handshake, not to the odometry
    rep = PioneerReplay(time_scale=SCALE, tx_chunks=[c.data for c in rec.capture.chunks if c.direction == "tx"])
    odoms = replay(rec.capture, rep)
    assert rep.session.links == 2 and rep.session.stats.sips >= len(live)
    assert len(odoms) == base.stats.sips  # live: the callback was added after the first SIP(s)
    odoms = odoms[-len(live):]
    got = np.array([(o.x, o.y, o.yaw, o.v, o.omega) for o in odoms])
    want = np.array([(o.x, o.y, o.yaw, o.v, o.omega) for o in live])
    assert np.allclose(got, want, atol=1e-12, rtol=0)
    assert np.allclose(odoms[-1].covariance, live[-1].covariance, atol=1e-15)


@pytest.mark.parametrize("session", SESSIONS, ids=[s.name for s in SESSIONS])
def test_raw_replay_of_the_committed_captures_skips_the_handshake_like_the_client(session):
    cap = Capture.load(session.path)
    info, n_sips, final = offline(cap)
    rep = PioneerReplay(tx_chunks=[c.data for c in cap.chunks if c.direction == "tx"])
    odoms = replay(cap, rep)
    assert rep.session.info == info
    assert len(odoms) == n_sips  # SIPs of a still-open robot before the handshake are not odometry
    assert (odoms[-1].x, odoms[-1].y, odoms[-1].yaw) == pytest.approx((final.x, final.y, final.yaw), abs=1e-12)
