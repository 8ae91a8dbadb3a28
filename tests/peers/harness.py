"""Run third-party peers (AriaCoda examples, urg_library samples) against our emulators and record the bytes.

The peers are GPL/LGPL programs built outside this repository (see tests/fakes/captures/README.md); they are
only executed here, never copied. A session runs one peer binary against an emulator over a pty or
loopback TCP, records both directions with an emulator tap, and returns the capture with the peer's output
and what the emulator saw (commands, true pose, distance travelled).

Peer fixtures (tests/fakes/captures/peer-*.jsonl) are recorded with::

    .venv/bin/python -m tests.peers.harness --aria /work/peers/AriaCoda --urg /work/peers/urg_library/current

and their JSON note records the peer, its commit, the command and the measured result.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from drivers.capture import Capture, CaptureRecorder
from drivers.hokuyo.emulator import HokuyoEmulator, room_scan_source
from drivers.pioneer.emulator import PioneerEmulator

CAPTURE_DIR = Path(__file__).resolve().parents[1] / "fakes" / "captures"
ARIA_ENV = "GLASSMAP_ARIA_EXAMPLES"  # .../AriaCoda/examples of a built AriaCoda (lib/libAria.so beside it)
URG_ENV = "GLASSMAP_URG_SAMPLES"  # .../urg_library/current/samples/c with the samples built


@dataclass(frozen=True)
class AriaSession:
    """One ARIA program run against the Pioneer emulator.

    program: path relative to the AriaCoda root. distance: metres the program should drive (the sum of its
    speed x duration steps). heading: degrees its final heading should be (None: not checked).
    """

    name: str
    program: str
    link: str
    distance: float
    heading: float | None = None
    args: tuple[str, ...] = ()


ARIA_SESSIONS = (
    AriaSession("aria-simpleConnect", "examples/simpleConnect", "pty", 0.0, 0.0),
    # 250 mm/s x 5 s, turn +10 deg/s x 5 s and -10 deg/s x 10 s, 150 mm/s x 5 s: 2.0 m, heading -50 deg
    AriaSession("aria-simpleMotionCommands", "examples/simpleMotionCommands", "pty", 2.0, -50.0),
    # VEL2 (300,100) 5 s, VEL2 (200,200) 3 s, VEL 200 3 s, VEL2 (0,200) 5 s then RVEL +-50 deg/s 10 s (RVEL
    # replaces only the rotation: the 100 mm/s of VEL2 (0,200) carries on), HEAD turns, VEL2 (200,0) 5 s: 4.2 m
    AriaSession("aria-vel2Test", "tests/vel2Test", "tcp", 4.2),
)


@dataclass(frozen=True)
class UrgSession:
    """One urg_library sample run against the Hokuyo emulator over a pty (``-s PATH``)."""

    name: str
    program: str
    expect: tuple[str, ...] = ()  # substrings its output must contain


URG_SESSIONS = (
    UrgSession("urg-sensor_parameter", "sensor_parameter", ("UTM-30LX-EW", "step: [-540, 540]", "sensor data size: 1081")),
    UrgSession("urg-get_distance", "get_distance"),
    UrgSession("urg-get_distance_intensity", "get_distance_intensity"),
    UrgSession("urg-get_multiecho_intensity", "get_multiecho_intensity"),
    UrgSession("urg-sync_time_stamp", "sync_time_stamp"),
    UrgSession("urg-get_multiecho", "get_multiecho"),
    UrgSession("urg-calculate_xy", "calculate_xy"),
    UrgSession("urg-get_distance_handshake", "get_distance_handshake", ("[mm]",)),
    UrgSession("urg-timeout_test", "timeout_test", ("n = 0",)),  # nothing unasked-for within 3 s
    UrgSession("urg-reboot_test", "reboot_test"),
    UrgSession("urg-angle_convert_test", "angle_convert_test", ("urg_step2deg(540): 135.000000",)),
)


@dataclass
class PeerRun:
    capture: Capture
    output: str
    returncode: int
    result: dict = field(default_factory=dict)


def git_commit(path: Path) -> str:
    """The peer's commit: a ``PEER_COMMIT`` file in its root (source exported with git archive), else git."""
    for p in (path, *path.parents):
        f = p / "PEER_COMMIT"
        if f.exists():
            return f.read_text().strip()
    try:
        return subprocess.run(["git", "-C", str(path), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


async def _run(cmd: list[str], env: dict, cwd: Path, timeout: float) -> tuple[str, int]:
    proc = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE, stdin=asyncio.subprocess.DEVNULL,
                                                stderr=asyncio.subprocess.STDOUT, env=env, cwd=str(cwd))
    try:
        out, _ = await asyncio.wait_for(proc.communicate(), timeout)
    except asyncio.TimeoutError:
        proc.kill()
        out, _ = await proc.communicate()
        return out.decode(errors="replace") + "\n[timed out]", -9
    return out.decode(errors="replace"), proc.returncode


def _closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


async def run_aria(root: Path, session: AriaSession, timeout: float = 150.0) -> PeerRun:
    """Run one ARIA program against a real-robot Pioneer emulator (real time); record both directions."""
    emu = PioneerEmulator(seed=0)
    rec = CaptureRecorder("pioneer")
    emu.taps.append(rec)
    url = await (emu.serve_pty() if session.link == "pty" else emu.serve_tcp())
    if session.link == "pty":
        # ARIA first tries a simulator on localhost TCP: point that try at a port nobody listens on
        target = ["-robotPort", url.split("://", 1)[1].split("?", 1)[0], "-remoteRobotTcpPort", str(_closed_port())]
    else:
        target = ["-remoteHost", "127.0.0.1", "-remoteRobotTcpPort", url.rsplit(":", 1)[1]]
    env = dict(os.environ, ARIA=str(root), LD_LIBRARY_PATH=str(root / "lib"))
    try:
        out, rc = await _run([str(root / session.program), *target, *session.args], env, root, timeout)
        await asyncio.sleep(0.2)
    finally:
        await emu.close()
    x, y, th = (float(v) for v in emu.robot.true_pose)
    result = dict(distance_m=round(emu.robot.distance, 4), x_m=round(x, 4), y_m=round(y, 4),
                  heading_deg=round(math.degrees(th), 2), hostbaud=emu.hostbaud,
                  commands=sorted({c.cmd for c in emu.received}))
    return PeerRun(rec.capture, out, rc, result)


async def run_urg(samples: Path, session: UrgSession, timeout: float = 60.0) -> PeerRun:
    """Run one urg_library sample against the Hokuyo emulator over a pty (real time); record both directions."""
    emu = HokuyoEmulator(room_scan_source())
    rec = CaptureRecorder("hokuyo")
    emu.taps.append(rec)
    url = await emu.serve_pty()
    try:
        out, rc = await _run([str(samples / session.program), "-s", url.split("://", 1)[1]], dict(os.environ),
                             samples, timeout)
        await asyncio.sleep(0.1)
    finally:
        await emu.close()
    return PeerRun(rec.capture, out, rc, {"returncode": rc})


def note(peer: str, commit: str, command: str, transport: str, result: dict) -> str:
    return json.dumps({"kind": "peer", "peer": peer, "commit": commit, "command": command,
                       "transport": transport, "result": result})


async def record_all(aria: Path | None, urg: Path | None, out: Path) -> None:
    if aria is not None:
        commit = git_commit(aria)
        for s in ARIA_SESSIONS:
            run = await run_aria(aria, s)
            print(f"{s.name}: rc={run.returncode} {run.result}")
            if run.returncode != 0:
                print(run.output[-2000:])
                continue
            run.capture.note = note("AriaCoda", commit, f"{s.program} -robotPort PTY -remoteRobotTcpPort CLOSED_PORT" if s.link == "pty" else
                                    f"{s.program} -remoteHost 127.0.0.1 -remoteRobotTcpPort PORT", s.link,
                                    run.result)
            run.capture.save(out / f"peer-{s.name}.jsonl")
    if urg is not None:
        commit = git_commit(urg)
        for s in URG_SESSIONS:
            run = await run_urg(urg, s)
            print(f"{s.name}: rc={run.returncode}")
            if run.returncode != 0 or not all(e in run.output for e in s.expect):
                print(run.output[-2000:])
                continue
            run.capture.note = note("urg_library", commit, f"samples/c/{s.program} -s PTY", "pty", run.result)
            run.capture.save(out / f"peer-{s.name}.jsonl")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--aria", type=Path, help="root of a built AriaCoda (lib/libAria.so, examples/, tests/)")
    ap.add_argument("--urg", type=Path, help="directory of the built urg_library C samples")
    ap.add_argument("--out", type=Path, default=CAPTURE_DIR)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    asyncio.run(record_all(a.aria, a.urg, a.out))


if __name__ == "__main__":
    main(sys.argv[1:])
