"""One receive path: the bytes a live client read, fed again to the same session by the raw replay, give
the same scans (multi-echo too) (faults and reconnections included)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.capture import CaptureRecorder
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.emulator import Faults, HokuyoEmulator, room_scan_source
from runtime.raw_replay import HokuyoReplay
from tests.fakes.replay import feed_capture

pytestmark = pytest.mark.timeout(60)


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
    replayed = feed_capture(rec.capture, rep)[:len(live)]
    assert rep.session.links == 2 + 1  # the session's own first link, then the reconnection and the close
    assert [s.seq for s in replayed] == [s.seq for s in live]
    assert [s.sensor_stamp for s in replayed] == [s.sensor_stamp for s in live]
    for r, s in zip(replayed, live):
        assert s.echoes is not None and same(r.echoes, s.echoes) and same(r.echo_intensities, s.echo_intensities)
        assert same(r.ranges, s.ranges) and same(r.intensities, s.intensities) and r.geometry == s.geometry
    # host stamps: the capture's clock starts at its first chunk; relative stamps agree
    d_live = np.diff([s.stamp for s in live])
    d_rep = np.diff([s.stamp for s in replayed])
    assert np.allclose(d_rep, d_live, atol=1e-5)  # the taps record the times the session saw
    assert rep.session.stats.corrupted >= stats.corrupted  # the replay also sees what came after the close
