"""One receive path: the bytes a live client read, fed again to the same session by the raw replay, give
the same odometry (faults and reconnections included)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from drivers.capture import Capture, CaptureRecorder
from drivers.pioneer.client import PioneerClient
from runtime.raw_replay import PioneerReplay
from tests.pioneer.conftest import SCALE, fast_settings
from tests.fakes.pioneer_captures import decode_rx
from tests.pioneer.make_captures import SESSIONS
from tests.fakes.replay import feed_capture

pytestmark = pytest.mark.timeout(60)


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
    odoms = feed_capture(rec.capture, rep)
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
    info, n_sips, final = decode_rx(cap)
    rep = PioneerReplay(tx_chunks=[c.data for c in cap.chunks if c.direction == "tx"])
    odoms = feed_capture(cap, rep)
    assert rep.session.info == info
    assert len(odoms) == n_sips  # SIPs of a still-open robot before the handshake are not odometry
    assert (odoms[-1].x, odoms[-1].y, odoms[-1].yaw) == pytest.approx((final.x, final.y, final.yaw), abs=1e-12)
