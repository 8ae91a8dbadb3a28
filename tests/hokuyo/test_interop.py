"""Interop: hokuyolx (a third-party SCIP client from PyPI) reads scans from our emulator.

hokuyolx speaks TCP with blocking sockets, so it runs in a thread while the emulator serves in the event
loop. Its known limits shape the session: it assumes one reply per read (our emulator writes one reply
per write and runs in real time so hokuyolx keeps up), and it sends %ST when it time-syncs or forces
standby, which the UTM-30LX-EW does not define (0E): so it is opened with tsync=False, convert_time=False.
"""

import asyncio

import numpy as np
import pytest

from drivers.hokuyo.client import HokuyoClient
from drivers.hokuyo.emulator import HokuyoEmulator, canned_scan_source, ranges_to_codes

import hokuyolx  # noqa: E402  (a test dependency: pyproject [test] extra)

pytestmark = pytest.mark.timeout(60)


def source():
    rng = np.random.default_rng(11)
    r = rng.uniform(0.1, 29.0, 1081)
    r[100:110] = np.inf  # no return -> code 1
    inten = rng.uniform(0, 12000, 1081)
    return r, inten


def hokuyolx_session(port: int):
    lx = hokuyolx.HokuyoLX(addr=("127.0.0.1", port), tsync=False, info=True, activate=False,
                           convert_time=False)
    try:
        info = (lx.model, lx.dmin, lx.dmax, lx.ares, lx.amin, lx.amax, lx.aforw, lx.scan_freq)
        code, _ = lx.activate()
        ts, single = lx.get_intens()
        stream = [(scan, t, pending) for scan, t, pending in lx.iter_intens(scans=3)]
        version = lx.version()
        lx.standby()
    finally:
        lx.close()
    return info, code, single, stream, version


async def test_hokuyolx_reads_the_same_values_as_our_client():
    r, inten = source()
    emu = HokuyoEmulator(canned_scan_source(r, inten), time_scale=1.0)
    url = await emu.serve_tcp()
    port = int(url.rsplit(":", 1)[1])
    info, code, single, stream, version = await asyncio.to_thread(hokuyolx_session, port)
    assert info == ("UTM-30LX-EW", 23, 60000, 1440, 0, 1080, 540, 40)
    assert code == 0 and version["PROT"] == "SCIP 2.0"
    want_d = ranges_to_codes(r)
    want_i = np.rint(inten).astype(int)
    assert single.shape == (1081, 2)
    assert np.array_equal(single[:, 0], want_d) and np.array_equal(single[:, 1], want_i)
    assert [pending for _, _, pending in stream] == [2, 1, 0]
    for scan, _, _ in stream:
        assert np.array_equal(scan[:, 0], want_d) and np.array_equal(scan[:, 1], want_i)
    stamps = [t for _, t, _ in stream]
    assert np.diff(stamps).tolist() == [25, 25]

    async with HokuyoClient.connect(url) as client:
        async for ours in client.scans():
            break
    assert np.array_equal(np.rint(ours.ranges[np.isfinite(ours.ranges)] * 1000), single[:, 0][np.isfinite(ours.ranges)])
    assert np.isinf(ours.ranges[100:110]).all()
    assert np.array_equal(ours.intensities, single[:, 1])
    await emu.close()
