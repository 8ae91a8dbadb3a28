"""Record the committed Pioneer byte captures (tests/fakes/captures/pioneer-*.jsonl).

Each capture is a real session of :class:`drivers.pioneer.client.PioneerClient` against the emulator over
a pseudo-terminal, in real time, recorded by a :class:`drivers.capture.CaptureRecorder` tap. Regenerate
with ``.venv/bin/python -m tests.pioneer.make_captures`` (the replay tests read them back).
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from pathlib import Path

from drivers.capture import CaptureRecorder
from drivers.pioneer.client import PioneerClient, PioneerSettings
from drivers.pioneer.emulator import EmulatorFaults, PioneerEmulator

CAPTURE_DIR = Path(__file__).resolve().parents[1] / "fakes" / "captures"


@dataclass(frozen=True)
class Session:
    """One recorded session: emulator options, client options, what the client does."""

    name: str
    note: str
    subclass: str = "p3dx-sh"
    real_robot: bool = True
    still_open: bool = False
    read_config: bool = False
    enable_motors: bool = False
    drive: tuple[float, float, float] | None = None  # v m/s, omega rad/s, seconds
    sips: int = 10

    @property
    def path(self) -> Path:
        return CAPTURE_DIR / f"pioneer-{self.name}.jsonl"

    def settings(self, **kw) -> PioneerSettings:
        return PioneerSettings(read_config=self.read_config, **kw)


SESSIONS = (
    Session("p3dx-sh-connect", "handshake, OPEN, CONFIG, 10 SIPs, close; real-robot emulator p3dx-sh",
            read_config=True),
    Session("p3dx-drive", "p3dx (0.485 mm/unit): ENABLE, drive 0.3 m/s turning 10 deg/s for 2 s, close",
            subclass="p3dx", enable_motors=True, drive=(0.3, math.radians(10), 2.0), sips=5),
    Session("still-open", "robot left open by an earlier session: SIPs before SYNC0, CLOSE, drain, handshake",
            still_open=True, sips=5),
    Session("sim-deviations", "simulator behaviour: 0x32 while moving, 16-bit positions, motors on, all sonar",
            real_robot=False, drive=(-0.2, 0.0, 1.0), sips=5),
)


async def record(session: Session) -> None:
    emu = PioneerEmulator(subclass=session.subclass, real_robot=session.real_robot,
                          faults=EmulatorFaults(still_open=session.still_open), seed=0)
    url = await emu.serve_pty()
    if session.still_open:
        await asyncio.sleep(0.35)  # the stale session has been streaming SIPs into the line
    rec = CaptureRecorder("pioneer", note=session.note)
    try:
        async with PioneerClient.connect(url, enable_motors=session.enable_motors, taps=[rec],
                                         settings=session.settings()) as base:
            if session.drive is not None:
                v, w, secs = session.drive
                for _ in range(int(secs / 0.1)):
                    await base.set_velocity(v, w)
                    await asyncio.sleep(0.1)
                await base.stop()
            n = 0
            async for _ in base.odometry():
                n += 1
                if n >= session.sips:
                    break
    finally:
        await emu.close()
    rec.capture.save(session.path)
    print(f"{session.path}: {len(rec.capture.chunks)} chunks, {len(rec.capture.rx_bytes())} bytes rx, "
          f"{len(rec.capture.tx_bytes())} bytes tx")


async def main() -> None:
    CAPTURE_DIR.mkdir(parents=True, exist_ok=True)
    for s in SESSIONS:
        await record(s)


if __name__ == "__main__":
    asyncio.run(main())
