"""Live interop: the reference clients, built outside this repository, against our emulators (opt-in).

``pytest -m interop`` with
- ``GLASSMAP_ARIA_EXAMPLES=/path/to/AriaCoda/examples`` (a built AriaCoda: lib/libAria.so, examples/
  simpleConnect and simpleMotionCommands, tests/vel2Test), and/or
- ``GLASSMAP_URG_SAMPLES=/path/to/urg_library/current/samples/c`` (the built C samples).
Each program runs in real time against an emulator; ARIA's programs must drive the emulated robot the
distance they command.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import pytest

from tests.peers.harness import ARIA_ENV, ARIA_SESSIONS, URG_ENV, URG_SESSIONS, run_aria, run_urg

pytestmark = [pytest.mark.interop, pytest.mark.timeout(300)]


def peer_dir(env: str) -> Path:
    value = os.environ.get(env)
    if not value:
        pytest.skip(reason=f"set {env} to run this peer live")
    path = Path(value)
    if not path.is_dir():
        pytest.fail(f"{env}={value} is not a directory")
    return path


@pytest.mark.parametrize("session", ARIA_SESSIONS, ids=lambda s: s.name)
async def test_aria_program_drives_the_emulated_robot(session):
    root = peer_dir(ARIA_ENV).parent
    if not (root / session.program).exists():
        pytest.fail(f"{root / session.program} is not built")
    run = await run_aria(root, session)
    assert run.returncode == 0, run.output[-2000:]
    assert "Connected to robot." in run.output and "Could not connect" not in run.output.replace(
        "Could not connect to simulator", "")  # its first, expected try: a simulator on localhost TCP
    assert "below 0, ignoring" not in run.output
    r = run.result
    assert r["distance_m"] == pytest.approx(session.distance, rel=0.05, abs=0.02), r
    if session.heading is not None:
        assert abs(r["heading_deg"] - session.heading) < 3.0, r
    if session.link == "pty":
        assert r["hostbaud"] == 2 and "did not switch to baud" not in run.output  # 38400 after CONFIG
    if session.distance:
        assert math.hypot(r["x_m"], r["y_m"]) > 0.5


@pytest.mark.parametrize("session", URG_SESSIONS, ids=lambda s: s.name)
async def test_urg_sample_reads_the_emulated_sensor(session):
    samples = peer_dir(URG_ENV)
    if not (samples / session.program).exists():
        pytest.fail(f"{samples / session.program} is not built")
    run = await run_urg(samples, session)
    assert run.returncode == 0, run.output[-2000:]
    errors = [ln for ln in run.output.splitlines() if re.match(r"urg_\w+: ", ln)]  # e.g. "urg_open: ..."
    assert not errors, run.output[-2000:]
    for text in session.expect:
        assert text in run.output, run.output[-2000:]
