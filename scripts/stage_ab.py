"""Interleaved before/after stage profiles of two checkouts on one recording (docs/performance.md).

On a machine whose speed drifts from minute to minute, two benchmark runs made at different times compare
the machine more than the code. This runs ``runtime.stageprof.stage_profile`` on the recording's raw bytes
in a fresh process of checkout A, then of checkout B, then A again, ... (``--pairs`` times, ``--runs``
profiles per process) and prints, per stage, the median and range of the CPU ms per scan of each, their
ratio, and the rate in scans per second of CPU time. ``--pinned``: each pair also replays the raw bytes once
per checkout in a process pinned to one CPU (Linux), the wall-clock rate on one core, literally.

    python scripts/stage_ab.py BEFORE_DIR AFTER_DIR RECORDING.mcap [--pairs 6] [--runs 3] [--pinned]

Each checkout runs its own code (``PYTHONPATH`` = the checkout) with this interpreter. A recording:
``glassmap bench --out DIR`` leaves one as ``DIR/demo.mcap``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

_CHILD = """
import json, sys
from runtime.stageprof import stage_profile
for _ in range(int(sys.argv[2])):
    t = stage_profile(sys.argv[1], "raw")
    n = max(t.scans, 1)
    d = {k: 1e3 * v / n for k, v in t.cpu.items()}
    d["all threads from the first scan to the last"] = 1e3 * t.process_cpu / n
    d["processing (stages, replay loop)"] = 1e3 * t.processing_cpu / n
    d["reading and decoding"] = 1e3 * t.reader_cpu / n
    d["other threads"] = 1e3 * (t.process_cpu - t.processing_cpu - t.reader_cpu) / n
    d["scans per second of CPU time"] = n / t.process_cpu
    print("STAGES " + json.dumps(d), flush=True)
"""


def profile(tree: Path, recording: Path, runs: int) -> list[dict]:
    """``runs`` stage profiles of ``recording`` by the code of checkout ``tree``, in one fresh process."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", _CHILD, str(recording), str(runs)], cwd=tree, env=env,
                         capture_output=True, text=True)
    rows = [json.loads(line[7:]) for line in out.stdout.splitlines() if line.startswith("STAGES ")]
    if out.returncode or len(rows) != runs:
        raise SystemExit(f"{tree}: the stage profile failed (exit {out.returncode}):\n{out.stderr[-2000:]}")
    return rows


def pinned(tree: Path, recording: Path) -> float:
    """Scans per second (wall clock) of a raw replay of ``recording`` by checkout ``tree``, pinned to one CPU."""
    from runtime.bench import PinnedReplayError, pinned_replay

    try:
        got = pinned_replay(recording, root=tree)
    except PinnedReplayError as exc:
        raise SystemExit(f"{tree}: {exc}") from None
    if got is None:
        raise SystemExit("--pinned: CPU affinity cannot be set on this system (Linux only)")
    return got[1]["rate"]


def table(before: list[dict], after: list[dict]) -> str:
    """Markdown table: per stage, median (min-max) before and after, and after / before of the medians."""
    lines = ["| stage | before: median (min-max) | after: median (min-max) | after / before |", "|---|---|---|---|"]
    for key in after[0]:
        a, b = [r[key] for r in before if key in r], [r[key] for r in after]
        if not a:
            continue
        fmt = "{:.0f}" if key.startswith("scans per second") else "{:.3f}"
        cell = lambda v: f"{fmt.format(statistics.median(v))} ({fmt.format(min(v))}-{fmt.format(max(v))})"
        ratio = statistics.median(b) / statistics.median(a) if statistics.median(a) else float("nan")
        lines.append(f"| {key} | {cell(a)} | {cell(b)} | {ratio:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path, help="checkout with the code before the change")
    ap.add_argument("after", type=Path, help="checkout with the code after the change")
    ap.add_argument("recording", type=Path, help="a glassmap recording with raw bytes (e.g. glassmap bench's demo.mcap)")
    ap.add_argument("--pairs", type=int, default=6, help="before/after process pairs, in turn (default 6)")
    ap.add_argument("--runs", type=int, default=3, help="stage profiles per process (default 3)")
    ap.add_argument("--pinned", action="store_true", help="also one replay per checkout and pair pinned to one CPU")
    args = ap.parse_args(argv)
    for tree in (args.before, args.after):
        if not (tree / "runtime" / "stageprof.py").is_file():
            ap.error(f"{tree} is not a glassmap checkout (no runtime/stageprof.py)")
    if not args.recording.is_file():
        ap.error(f"no recording {args.recording}")
    if args.pairs < 1 or args.runs < 1:
        ap.error("--pairs and --runs must be >= 1")
    before: list[dict] = []
    after: list[dict] = []
    rates: dict[Path, list[float]] = {args.before: [], args.after: []}
    for i in range(args.pairs):
        for tree, rows in ((args.before, before), (args.after, after)):
            rows += profile(tree.resolve(), args.recording.resolve(), args.runs)
            rate = statistics.median(r["scans per second of CPU time"] for r in rows)
            if args.pinned:
                rates[tree].append(pinned(tree, args.recording))
            print(f"pair {i + 1}/{args.pairs} {tree}: median so far {rate:.0f} scans/s of CPU time", file=sys.stderr)
    print(f"{len(before)} + {len(after)} stage profiles of {args.recording}, interleaved, CPU ms per scan")
    print(table(before, after))
    if args.pinned:
        a, b = rates[args.before], rates[args.after]
        print(f"pinned to one CPU, wall clock (scans/s), {len(a)} + {len(b)} replays: before median {statistics.median(a):.0f} "
              f"({min(a):.0f}-{max(a):.0f}), after {statistics.median(b):.0f} ({min(b):.0f}-{max(b):.0f}); pairwise "
              f"after / before median {statistics.median(y / x for x, y in zip(a, b)):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
