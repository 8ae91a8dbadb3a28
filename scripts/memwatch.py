"""Run a command and sample /proc/PID/smaps_rollup of it and of its descendants every 0.1 s; print each
process's peak Rss, Pss, Anonymous, Pss_Anon and Pss_File (MiB; each field's own peak). Linux only.

Usage: python scripts/memwatch.py glassmap demo --duration 20 --no-progress
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

FIELDS = ("Rss", "Pss", "Anonymous", "Pss_Anon", "Pss_File")


def descendants(pid: int) -> list[int]:
    out = [pid]
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                for child in f.read().split():
                    out += descendants(int(child))
    except OSError:
        pass
    return out


def rollup(pid: int) -> dict[str, int] | None:
    """smaps_rollup fields in KiB, or None when the process is gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            rows = [line.split() for line in f]
    except OSError:
        return None
    return {r[0].rstrip(":"): int(r[1]) for r in rows if len(r) >= 3 and r[-1] == "kB"}


def main(argv: list[str]) -> int:
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL)
    peak: dict[int, dict[str, int]] = {}
    names: dict[int, str] = {}
    while proc.poll() is None:
        for pid in descendants(proc.pid):
            d = rollup(pid)
            if d is None:
                continue
            if pid not in names:
                try:
                    with open(f"/proc/{pid}/cmdline") as f:
                        names[pid] = f.read().replace("\0", " ")[:80]
                except OSError:
                    names[pid] = "?"
            p = peak.setdefault(pid, {})
            for k in FIELDS:
                p[k] = max(p.get(k, 0), d.get(k, 0))
        time.sleep(0.1)
    for pid, p in peak.items():
        print(pid, " ".join(f"{k}={p[k] / 1024:.0f}" for k in FIELDS), "MiB", names[pid])
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
