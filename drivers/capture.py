"""Recorded byte streams ("captures"): both directions of a device link with host timestamps.

File format (``.jsonl``): one JSON object per line. The first line is a header
``{"format": "glassmap-capture", "version": 1, "device": "...", "note": "..."}``; each further line is one
chunk ``{"t": seconds since the first chunk, "dir": "rx" | "tx", "data": "<base64>"}`` where ``rx`` is
device -> host and ``tx`` host -> device, in the order seen on the wire.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from pathlib import Path




@dataclass(frozen=True)
class Chunk:
    t: float
    direction: str
    data: bytes


@dataclass
class Capture:
    device: str
    chunks: list[Chunk] = field(default_factory=list)
    note: str = ""

    def rx_bytes(self) -> bytes:
        return b"".join(c.data for c in self.chunks if c.direction == "rx")

    def tx_bytes(self) -> bytes:
        return b"".join(c.data for c in self.chunks if c.direction == "tx")

    def save(self, path: str | Path) -> None:
        with open(path, "w", encoding="ascii") as f:
            f.write(json.dumps({"format": "glassmap-capture", "version": 1, "device": self.device,
                                "note": self.note}) + "\n")
            for c in self.chunks:
                f.write(json.dumps({"t": c.t, "dir": c.direction,
                                    "data": base64.b64encode(c.data).decode("ascii")}) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Capture:
        path = Path(path)
        with open(path, encoding="ascii") as f:
            lines = f.read().splitlines()
        if not lines:
            raise ValueError(f"{path}: empty capture file")
        header = json.loads(lines[0])
        if header.get("format") != "glassmap-capture":
            raise ValueError(f"{path}:1: not a glassmap capture (header {lines[0][:80]!r})")
        cap = cls(device=header.get("device", ""), note=header.get("note", ""))
        for n, line in enumerate(lines[1:], start=2):
            try:
                obj = json.loads(line)
                if obj["dir"] not in ("rx", "tx"):
                    raise ValueError(f"dir must be rx or tx, got {obj['dir']!r}")
                cap.chunks.append(Chunk(float(obj["t"]), obj["dir"], base64.b64decode(obj["data"])))
            except (KeyError, ValueError, TypeError) as exc:
                raise ValueError(f"{path}:{n}: bad chunk ({exc})") from exc
        return cap


class CaptureRecorder:
    """A transport tap that records every chunk: ``transport.taps.append(recorder)``."""

    def __init__(self, device: str, note: str = "") -> None:
        self.capture = Capture(device=device, note=note)
        self._t0: float | None = None

    def __call__(self, direction: str, host_time: float, data: bytes) -> None:
        if self._t0 is None:
            self._t0 = host_time
        self.capture.chunks.append(Chunk(round(host_time - self._t0, 6), direction, bytes(data)))
