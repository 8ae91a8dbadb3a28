"""Decode throughput of 1081-step ME scans: this codec against hokuyolx's decoder, on the same bytes.

Both sides get whole scan messages as they come off the wire (one per read, the common case) and produce
the distance and intensity integers: ours with :class:`ScipParser` (checksums verified, vectorized), the
reference with the per-scan work hokuyolx does in ``HokuyoLX._iter_meas`` (split lines, check the status
and every checksum, timestamp, ``_process_scan_data``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from drivers.hokuyo.scip import ScipParser, ScanReply, encode_reply, encode_scan_payload


@dataclass(frozen=True)
class BenchResult:
    scans: int
    ours_scans_per_s: float
    hokuyolx_scans_per_s: float | None

    @property
    def speedup(self) -> float | None:
        return None if not self.hokuyolx_scans_per_s else self.ours_scans_per_s / self.hokuyolx_scans_per_s


def make_messages(n: int, seed: int = 0) -> list[bytes]:
    """``n`` ME stream messages of 1081 steps with random distances (mm) and intensities."""
    rng = np.random.default_rng(seed)
    msgs = []
    for k in range(n):
        d = rng.integers(23, 30000, 1081)
        i = rng.integers(0, 12000, 1081)
        msgs.append(encode_reply(b"ME0000108001000", "99", encode_scan_payload("ME", 1000 + 25 * k, d, i)))
    return msgs


def decode_ours(msgs: list[bytes]) -> list[ScanReply]:
    parser = ScipParser()
    out = []
    for m in msgs:
        out.extend(parser.feed(m))
    return out


def hokuyolx_available() -> bool:
    """Whether the reference decoder (the hokuyolx package, a test extra) can be imported."""
    import importlib.util

    return importlib.util.find_spec("hokuyolx") is not None


def decode_hokuyolx(msgs: list[bytes]) -> list[np.ndarray]:
    """hokuyolx's per-scan path (needs hokuyolx installed)."""
    from hokuyolx import HokuyoLX

    lx = HokuyoLX.__new__(HokuyoLX)  # no socket: only the decoding methods are used
    out = []
    for m in msgs:
        lines = m[:-2].decode("ascii").split("\n")
        lines.pop(0)
        lx._check_sum(lines.pop(0))
        lx._convert2ts(lines.pop(0), False)
        out.append(lx._process_scan_data(lines, True))
    return out


def _timed(fn, msgs: list[bytes], seconds: float) -> float:
    """scans/s of ``fn`` over ``msgs``, repeated for at least ``seconds``."""
    done, t0 = 0, time.perf_counter()
    while True:
        fn(msgs)
        done += len(msgs)
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return done / dt


def run_bench(n: int = 200, min_time: float = 1.0, with_hokuyolx: bool = True, seed: int = 0,
              rounds: int = 5) -> BenchResult:
    """Time both decoders on the same ``n`` messages, ``min_time`` seconds each in total.

    The two are timed in alternating rounds and the best round of each is kept, so that load from other
    processes (which only ever slows a round down) hits both alike."""
    msgs = make_messages(n, seed)
    ours = decode_ours(msgs)
    if len(ours) != n or not all(isinstance(r, ScanReply) for r in ours):
        raise RuntimeError("benchmark messages did not decode; the codec is broken")
    if with_hokuyolx:
        ref = decode_hokuyolx(msgs[:5])
        for a, b in zip(ours, ref):
            if not (np.array_equal(a.distances, b[:, 0]) and np.array_equal(a.intensities, b[:, 1])):
                raise RuntimeError("hokuyolx and this codec disagree on the benchmark data")
    best_ours = best_ref = 0.0
    for _ in range(rounds):
        best_ours = max(best_ours, _timed(decode_ours, msgs, min_time / rounds))
        if with_hokuyolx:
            best_ref = max(best_ref, _timed(decode_hokuyolx, msgs, min_time / rounds))
    return BenchResult(n, best_ours, best_ref if with_hokuyolx else None)
