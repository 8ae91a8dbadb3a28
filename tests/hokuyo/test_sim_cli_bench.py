"""The simulator-driven emulator, the ``glassmap hokuyo`` commands and the decode benchmark."""

import asyncio
import socket
import sys

import numpy as np
import pytest

from drivers.hokuyo.bench import make_messages, run_bench
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.emulator import HokuyoEmulator, room_scan_source, sim_scan_source

pytestmark = pytest.mark.timeout(60)


async def test_simulated_world_scans_reach_the_client_unchanged():
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    world = load_world("office")
    pose = np.asarray(world.start_pose, float)
    emu = HokuyoEmulator(sim_scan_source(world, lambda t: pose, seed=3), time_scale=2.0)
    url = await emu.serve_tcp()
    async with HokuyoClient.connect(url, HokuyoSettings(multi_echo=True)) as client:
        async for scan in client.scans():
            break
    await emu.close()
    truth = simulate_scan(world, pose, np.random.default_rng(3))  # the source's first scan
    fin = np.isfinite(truth.ranges) & (truth.ranges >= 0.023)
    assert np.allclose(scan.ranges[fin], truth.ranges[fin], atol=0.0006)
    assert np.array_equal(np.isinf(scan.ranges), np.isinf(truth.ranges))
    assert np.allclose(scan.intensities, np.clip(np.rint(truth.intensities), 0, (1 << 18) - 1))
    two = np.isfinite(truth.echo_ranges[:, 1]) & fin
    assert two.any() and np.allclose(scan.echoes[two, 0], truth.echo_ranges[two, 1], atol=0.0006)


async def run_cli(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "runtime.cli", "hokuyo", *args,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 40)
    return proc.returncode, out.decode(), err.decode()


async def test_cli_probe_stream_and_record_against_the_emulator(tmp_path):
    emu = HokuyoEmulator(room_scan_source(), time_scale=4.0)
    url = await emu.serve_tcp()
    code, out, err = await run_cli("probe", url)
    assert code == 0, err
    assert "MODL: UTM-30LX-EW" in out and "PROT: SCIP 2.0" in out and "AFRT: 540" in out and "LASR:" in out
    code, out, err = await run_cli("stream", url, "-n", "20", "--cluster", "2")
    assert code == 0, err
    assert "20 scans in" in out and "received=" in out and "541 beams" in out
    path = tmp_path / "rec.jsonl"
    code, out, err = await run_cli("record", url, str(path), "-n", "5")
    assert code == 0, err
    from drivers.capture import Capture

    cap = Capture.load(path)
    assert cap.device == "hokuyo" and cap.rx_bytes().count(b"\n99b\n") >= 5
    await emu.close()
    with socket.socket() as free:  # a port nobody listens on (port 1 may be in use on a busy machine)
        free.bind(("127.0.0.1", 0))
        dead = free.getsockname()[1]
    code, out, err = await run_cli("probe", f"tcp://127.0.0.1:{dead}")
    assert code == 1 and "error:" in err


def test_bench_decoders_agree_and_report_rates():
    msgs = make_messages(3)
    assert len(msgs) == 3 and all(m.endswith(b"\n\n") for m in msgs)
    r = run_bench(n=20, min_time=0.05)  # checks both decoders give the same numbers first
    assert r.ours_scans_per_s > 0 and r.hokuyolx_scans_per_s > 0 and r.speedup > 0


def test_bench_without_hokuyolx_skips_the_comparison_with_a_note(monkeypatch, capsys):
    import importlib.util

    from runtime.cli import main

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "hokuyolx" else real(name, *a))
    assert main(["hokuyo", "bench", "--scans", "5", "--seconds", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "hokuyolx is not installed: comparison skipped" in out
    assert "ours:" in out and "hokuyolx:" not in out
