"""The same client checks against a real UTM-30LX-EW (opt-in: ``-m hardware`` and a laser URL).

Give the URL with ``--laser-url`` or ``GLASSMAP_LASER_URL``, e.g.
``GLASSMAP_LASER_URL=tcp://192.168.0.10:10940 .venv/bin/python -m pytest -m hardware tests/hokuyo``.
"""


import numpy as np
import pytest

from drivers.hokuyo.client import HokuyoClient

pytestmark = [pytest.mark.hardware, pytest.mark.timeout(60)]


async def test_real_sensor_streams_consistent_scans(laser_url):
    async with HokuyoClient.connect(laser_url) as client:
        scans = []
        async for scan in client.scans():
            scans.append(scan)
            if len(scans) >= 80:
                break
        p = client.params
    assert p.amax - p.amin + 1 == scans[0].ranges.size
    assert client.stats.corrupted == 0 and client.stats.reconnects == 0
    period = p.scan_time
    assert np.allclose(np.diff([s.sensor_stamp for s in scans]), period, atol=0.0015)
    finite = np.isfinite(scans[-1].ranges)
    assert finite.any() and (scans[-1].ranges[finite] >= p.dmin / 1000).all()
