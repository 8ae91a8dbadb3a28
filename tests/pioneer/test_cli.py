"""``glassmap pioneer`` commands as separate processes against the emulator: probe, drive, Ctrl-C, SIGTERM."""

from __future__ import annotations

import asyncio
import re
import signal
import sys

import pytest

from drivers.pioneer.packets import Cmd
from tests.helpers import eventually
from tests.pioneer.conftest import SCALE

pytestmark = pytest.mark.timeout(60)


async def run_cli(*args: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable, "-m", "runtime.cli", "pioneer", *args, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE)


async def test_probe_prints_identity_and_sips(emulator_factory):
    emu, url = await emulator_factory()
    proc = await run_cli("probe", url, "--sips", "3", "--config", "--time-scale", str(SCALE))
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    text = out.decode()
    assert proc.returncode == 0, err.decode()
    assert "name: glassmap-emulator" in text and "class: Pioneer" in text and "subclass: p3dx-sh" in text
    assert text.count("SIP 0x32") == 3 and "motors=off" in text
    assert "watchdog=2000" in text
    await eventually(lambda: not emu.is_open, what="CLOSE")


async def test_probe_of_a_dead_port_fails_with_a_clear_message(tmp_path):
    proc = await run_cli("probe", f"serial://{tmp_path}/nothing")
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode == 1
    assert b"error:" in err and b"cannot open" in err


async def test_scripted_line(emulator_factory):
    emu, url = await emulator_factory()
    proc = await run_cli("drive", url, "--line", "0.3", "--speed", "0.3", "--time-scale", str(SCALE))
    out, err = await asyncio.wait_for(proc.communicate(), 40)
    assert proc.returncode == 0, err.decode()
    m = re.search(rb"final odometry: x=([-+.0-9]+) m", out)
    assert m and float(m.group(1)) == pytest.approx(0.3, abs=0.03)
    await eventually(lambda: not emu.is_open, what="CLOSE")
    assert [c.cmd for c in emu.received[-4:]] == [Cmd.VEL, Cmd.RVEL, Cmd.ENABLE, Cmd.CLOSE]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
async def test_signal_stops_the_robot(emulator_factory, sig):
    emu, url = await emulator_factory()
    proc = await run_cli("drive", url, "--line", "20", "--speed", "0.4", "--time-scale", str(SCALE))
    try:
        await eventually(lambda: emu.robot.velocity[0] > 0.2, timeout=30, what="robot moving")
        proc.send_signal(sig)
        out, err = await asyncio.wait_for(proc.communicate(), 20)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 128 + sig, err.decode()
    assert f"stopped by {sig.name}".encode() in err
    tail = [(c.cmd, c.arg) for c in emu.received[-4:]]
    assert tail == [(Cmd.VEL, 0), (Cmd.RVEL, 0), (Cmd.ENABLE, 0), (Cmd.CLOSE, None)]
    assert not emu.is_open and not emu.motors_enabled
    await eventually(lambda: emu.robot.velocity == (0.0, 0.0), what="robot at rest")


def test_bench_prints_figures(capsys):
    from runtime.cli import main

    assert main(["pioneer", "bench", "--packets", "500"]) == 0
    out = capsys.readouterr().out
    assert "packets/s" in out and "500/500 recovered" in out


@pytest.mark.parametrize("how", ["q", "ctrl-c"])
async def test_teleop_restores_the_terminal(emulator_factory, how):
    import os
    import termios

    emu, url = await emulator_factory()
    master, slave = os.openpty()
    before = termios.tcgetattr(slave)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "runtime.cli", "pioneer", "drive", url, "--teleop", "--time-scale", str(SCALE),
        stdin=slave, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        await eventually(lambda: emu.motors_enabled, timeout=30, what="motors enabled")
        await eventually(lambda: termios.tcgetattr(slave) != before, what="terminal in cbreak mode")
        os.write(master, b"wwww\x1b[A")  # 4 x w and one arrow-up: 0.25 m/s
        await eventually(lambda: emu.robot.velocity[0] > 0.2, what="robot moving")
        assert emu.commanded_velocity[0] == pytest.approx(0.25)
        if how == "q":
            os.write(master, b"q")
        else:
            proc.send_signal(signal.SIGINT)
        out, err = await asyncio.wait_for(proc.communicate(), 20)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        after = termios.tcgetattr(slave)
        os.close(master)
        os.close(slave)
    assert proc.returncode == (0 if how == "q" else 130), err.decode()
    assert after == before
    await eventually(lambda: not emu.is_open, what="CLOSE")
    assert [c.cmd for c in emu.received[-4:]] == [Cmd.VEL, Cmd.RVEL, Cmd.ENABLE, Cmd.CLOSE]


async def test_emulate_serves_until_ctrl_c():
    from drivers.pioneer.client import PioneerClient
    from tests.pioneer.conftest import fast_settings

    proc = await run_cli("emulate", "--tcp", "0", "--time-scale", str(SCALE), "--subclass", "p3dx")
    try:
        url = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode().strip()
        assert url.startswith("tcp://127.0.0.1:")
        async with PioneerClient.connect(url, settings=fast_settings()) as base:
            assert base.info.subclass == "p3dx"
        proc.send_signal(signal.SIGINT)
        await asyncio.wait_for(proc.wait(), 20)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0


FORGETFUL = """
import asyncio, sys
from drivers.pioneer.client import PioneerClient, PioneerSettings

async def main(url):
    base = await PioneerClient.connect(url, PioneerSettings(time_scale=float(sys.argv[2])), enable_motors=True)
    for _ in range(30):
        await base.set_velocity(0.3, 0.0)
        await asyncio.sleep(0.02)
    # returns without close(): asyncio.run tears the loop down, the atexit hook must stop the robot

asyncio.run(main(sys.argv[1]))
"""


@pytest.mark.parametrize("link", ["pty", "tcp"])
async def test_process_exit_without_close_still_stops_the_robot(emulator_factory, link):
    emu, url = await emulator_factory(link)
    proc = await asyncio.create_subprocess_exec(sys.executable, "-c", FORGETFUL, url, str(SCALE),
                                                stderr=asyncio.subprocess.PIPE)
    _, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode == 0, err.decode()
    await eventually(lambda: not emu.is_open, what="CLOSE from the atexit hook")
    tail = [(c.cmd, c.arg) for c in emu.received[-4:]]
    assert tail == [(Cmd.VEL, 0), (Cmd.RVEL, 0), (Cmd.ENABLE, 0), (Cmd.CLOSE, None)]
