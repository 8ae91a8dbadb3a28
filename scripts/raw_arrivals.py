"""When the laser's bytes reached the runtime: the read times of a recording's /raw/laser chunks (sensor ->
host), their spacing, and the gaps longer than a threshold after the start-up. At 40 Hz the chunks come every
25 ms; a long gap followed by chunks a few ms apart is a burst (a sensor, an emulator or an event loop that
was late and caught up).

Usage: python scripts/raw_arrivals.py RECORDING.mcap [--gap MS] [--skip S]
"""

from __future__ import annotations

import argparse

import numpy as np

from runtime.readers import iter_raw_chunks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording")
    ap.add_argument("--gap", type=float, default=45.0, help="report gaps longer than this (ms; default 45)")
    ap.add_argument("--skip", type=float, default=1.0, help="leave out the first S seconds (the handshake)")
    args = ap.parse_args()
    t = np.array([c.host_time for c in iter_raw_chunks(args.recording) if c.device == "laser" and c.direction == "rx"])
    if t.size < 3:
        raise SystemExit(f"{args.recording}: fewer than 3 laser chunks received (recorded without raw bytes?)")
    t = t[t - t[0] > args.skip]
    gaps = np.diff(t) * 1e3
    print(f"{t.size} laser chunks after the first {args.skip:g} s; spacing ms: median {np.median(gaps):.1f}, "
          f"p1 {np.percentile(gaps, 1):.1f}, p99 {np.percentile(gaps, 99):.1f}, max {gaps.max():.1f}")
    long_ = np.flatnonzero(gaps > args.gap)
    print(f"gaps over {args.gap:g} ms: {long_.size}")
    for i in long_:
        after = np.round(gaps[i + 1:i + 4], 1).tolist()
        print(f"  t = {t[i] - t[0] + args.skip:7.2f} s: {gaps[i]:.1f} ms, then {after} ms")


if __name__ == "__main__":
    main()
