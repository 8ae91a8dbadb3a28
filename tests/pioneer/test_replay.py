"""Committed byte captures of real client sessions, replayed over a pty to the client (golden files).

The captures were recorded from the emulator through the real client (see tests/pioneer/make_captures.py).
Replaying one checks that today's client still speaks the same handshake byte for byte and turns the same
robot bytes into the same odometry as an offline decode of the capture.
"""

from __future__ import annotations

import asyncio
import math

import pytest

from drivers.capture import Capture
from drivers.pioneer.client import PioneerClient
from drivers.pioneer.packets import PacketParser
from tests.fakes.replay import replay_over_pty
from tests.helpers import eventually
from tests.fakes.pioneer_captures import decode_rx
from tests.pioneer.make_captures import SESSIONS

pytestmark = pytest.mark.timeout(60)


def handshake_tx(capture: Capture) -> list[tuple[int, bytes]]:
    """The host's packets up to OPEN (the second packet with ID 1: SYNC1 comes first), and a CONFIG request."""
    pkts = [(p.pid, p.payload) for p in PacketParser().feed(capture.tx_bytes())]
    ones = [k for k, (pid, _) in enumerate(pkts) if pid == 1]
    end = ones[1] + 1
    if end < len(pkts) and pkts[end][0] == 18:
        end += 1
    return pkts[:end]


@pytest.mark.parametrize("session", SESSIONS, ids=[s.name for s in SESSIONS])
async def test_replayed_capture_gives_the_recorded_odometry(session):
    cap = Capture.load(session.path)
    assert cap.device == "pioneer" and cap.note == session.note
    info, n_sips, final = decode_rx(cap)
    assert info is not None and info.subclass == session.subclass and n_sips >= session.sips
    path, replayer, endpoint, task = await replay_over_pty(cap)
    try:
        # the replayer answers as fast as the client talks: run the client's clock 10x faster
        settings = session.settings(time_scale=10.0, sip_timeout=20.0, reconnect=False)
        async with PioneerClient.connect(f"serial://{path}", settings=settings) as base:
            assert base.info == info
            await eventually(lambda: base.stats.sips >= n_sips, timeout=30, what="all recorded SIPs")
            assert base.stats.sips == n_sips and base.stats.bad_checksum == 0
            odom = base.latest
            assert (odom.x, odom.y, odom.yaw) == pytest.approx((final.x, final.y, final.yaw), abs=1e-12)
            assert odom.covariance == pytest.approx(final.covariance)
            if session.drive is not None:
                v, w, secs = session.drive
                assert math.copysign(1, odom.x) == math.copysign(1, v) and abs(odom.x) > abs(v) * secs * 0.5
            if session.still_open:
                assert base.stats.still_open_recoveries == 1
        hs = handshake_tx(cap)
        sent = [(p.pid, p.payload) for p in PacketParser().feed(bytes(replayer.stats.tx_received))]
        assert sent[: len(hs)] == hs  # the same handshake, packet for packet
    finally:
        task.cancel()
        endpoint.close()
        await asyncio.sleep(0)
