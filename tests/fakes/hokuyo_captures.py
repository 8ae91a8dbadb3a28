"""Record the Hokuyo byte captures used as golden files by the replay tests.

Each capture is a real session of :class:`drivers.hokuyo.client.HokuyoClient` against the emulator,
recorded with a transport tap (:class:`drivers.capture.CaptureRecorder`). The capture's note is JSON: the
client settings (so a replay sends the same bytes), the raw 24-bit stamps of the scans the consumer took,
and the client's counters at the end. Re-record with::

    .venv/bin/python -m tests.fakes.hokuyo_captures [OUT_DIR]
"""

from __future__ import annotations

import asyncio
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from drivers.capture import Capture, CaptureRecorder
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.emulator import Faults, HokuyoEmulator, canned_scan_source, room_scan_source

CAPTURE_DIR = Path(__file__).parent / "captures"


def _two_echo_source():
    rng = np.random.default_rng(3)
    r = np.column_stack([rng.uniform(0.5, 20.0, 1081), np.full(1081, np.nan)])
    r[::4, 1] = r[::4, 0] + 1.5
    inten = np.column_stack([rng.uniform(100, 8000, 1081), np.full(1081, 700.0)])
    return canned_scan_source(r[None], inten[None])


# name -> (scan source factory, emulator faults, client settings, scans to take)
CAPTURES = {
    "hokuyo-me-stream": (room_scan_source, Faults(), {}, 8),
    "hokuyo-faults": (room_scan_source,
                      Faults(status_every=5, checksum_every=7, drop_every=9, garbage_every=4, coalesce_every=3,
                             seed=7),
                      {"cluster": 3}, 30),
    "hokuyo-ne-multiecho": (_two_echo_source, Faults(), {"multi_echo": True, "start_step": 300, "end_step": 780}, 6),
}


def stamps_of(scans) -> list[int]:
    return [int(round(s.sensor_stamp * 1000)) % (1 << 24) for s in scans]


async def record_capture(name: str) -> Capture:
    make_source, faults, settings, n = CAPTURES[name]
    emu = HokuyoEmulator(make_source(), faults=faults, clock_start_ms=1_234_567)
    url = await emu.serve_tcp()
    rec = CaptureRecorder("hokuyo")
    client = await HokuyoClient.connect(url, HokuyoSettings(**settings), taps=[rec])
    scans = []
    async for scan in client.scans():
        scans.append(scan)
        if len(scans) >= n:
            break
    await client.close()
    await emu.close()
    rec.capture.note = json.dumps({"settings": settings, "scans": n, "stamps": stamps_of(scans),
                                   "stats": asdict(client.stats)})
    return rec.capture


async def record_all(out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in CAPTURES:
        cap = await record_capture(name)
        path = out_dir / f"{name}.jsonl"
        cap.save(path)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else CAPTURE_DIR
    for p in asyncio.run(record_all(out)):
        print(f"wrote {p} ({p.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
