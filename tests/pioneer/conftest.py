"""Shared helpers of the Pioneer tests: emulators on pseudo-terminals, fast client settings, polling."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import pytest

from drivers.pioneer.client import PioneerSettings
from drivers.pioneer.emulator import PioneerEmulator

SCALE = 5.0  # the emulated robot runs 5x faster than real time in the hardware-in-the-loop tests


def fast_settings(**kw) -> PioneerSettings:
    """Client settings matched to an emulator at SCALE, with generous link timeouts for a loaded machine."""
    base = dict(time_scale=SCALE, sip_timeout=5.0, handshake_timeout=1.5, open_timeout=10.0,
                max_v=0.6, backoff_initial=0.5)
    base.update(kw)
    return PioneerSettings(**base)


@pytest.fixture
async def emulator_factory():
    made: list[PioneerEmulator] = []

    async def make(link: str = "pty", **kw) -> tuple[PioneerEmulator, str]:
        kw.setdefault("time_scale", SCALE)
        emu = PioneerEmulator(**kw)
        made.append(emu)
        url = await (emu.serve_pty() if link == "pty" else emu.serve_tcp())
        return emu, url

    yield make
    for emu in made:
        await emu.close()


async def drive_until(base, v: float, omega: float, pred: Callable[[], bool], timeout: float = 10.0,
                      what: str = "condition") -> None:
    """Keep commanding (v, omega) like a caller's control loop would, until ``pred`` holds."""
    end = time.monotonic() + timeout
    while True:
        await base.set_velocity(v, omega)
        if pred():
            return
        if time.monotonic() > end:
            pytest.fail(f"{what} did not happen within {timeout} s")
        await asyncio.sleep(0.01)
