"""Opt-in checks against a real Pioneer 3-DX (or a simulator): ``GLASSMAP_BASE_URL=serial:///dev/ttyUSB0
pytest -m hardware tests/pioneer`` (or ``--base-url URL``). The drive check also needs ``GLASSMAP_BASE_DRIVE=1`` and 1 m of free
space around the robot: it turns 30 degrees in place and back."""

from __future__ import annotations

import math
import os

import pytest

from drivers.pioneer.client import PioneerClient
from drivers.pioneer.odometry import MODELS

pytestmark = [pytest.mark.hardware, pytest.mark.timeout(60)]


async def test_real_robot_handshake_and_sips(base_url):
    async with PioneerClient.connect(base_url) as base:
        assert base.info.robot_class.lower() == "pioneer" and base.model.subclass in MODELS
        n = 0
        async for odom in base.odometry():
            assert math.isfinite(odom.x) and math.isfinite(odom.yaw)
            n += 1
            if n == 10:
                break
        assert 10.0 < base.state.battery_volts < 15.0
        assert base.stats.bad_checksum == 0


@pytest.mark.skipif(os.environ.get("GLASSMAP_BASE_DRIVE") != "1", reason="set GLASSMAP_BASE_DRIVE=1 to move")
async def test_real_robot_turns_and_returns(base_url):
    from drivers.pioneer.cli import turn_by

    async with PioneerClient.connect(base_url, enable_motors=True) as base:
        yaw0 = base.latest.yaw
        await turn_by(base, math.radians(30), math.radians(20))
        await turn_by(base, math.radians(-30), math.radians(20))
        assert abs(math.remainder(base.latest.yaw - yaw0, 2 * math.pi)) < math.radians(3)
