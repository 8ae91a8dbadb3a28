"""CPU time per scan of every process of a ``glassmap demo``, start-up excluded (docs/performance.md).

Runs ``glassmap demo --duration D`` for two durations, samples the CPU time (user + system, /proc) of every
thread of the runtime and of its child processes (emulated devices, map worker) while each runs, and prints
the difference between the two runs divided by the difference in scans received: what each process (the
runtime's event loop thread apart from its other threads) costs per scan once started. CPU time adds up
across the cores, so at demo speed S the processes need S * 40 * (ms per scan) / 1000 cores.

    python scripts/demo_cpu.py [--durations 10 30] [-- DEMO ARGS...]    (e.g. -- --speed 2 --world office)

Linux only (/proc). The figures move with the machine's load: say the load beside them.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time

from memwatch import descendants  # scripts/ is on sys.path when this runs as a script

TICK = os.sysconf("SC_CLK_TCK")


def _role(pid: int, root: int) -> str | None:
    try:
        with open(f"/proc/{pid}/cmdline") as f:
            cmd = f.read().split("\0")
    except OSError:
        return None
    if pid == root:
        return "runtime"
    if not any(cmd):
        return None  # exited (a zombie): its last sample stands
    if "runtime.devices" in cmd:
        return "emulated devices"
    joined = " ".join(cmd)
    return "map worker" if "multiprocessing" in joined else "child: " + joined[:38]


def run(duration: float, demo_args: list[str]) -> tuple[int, dict[str, float]]:
    """One demo run: (scans received, CPU seconds per process role; the runtime split into its event loop
    thread and the rest)."""
    out_dir = tempfile.mkdtemp(prefix="demo_cpu_")
    cmd = [sys.executable, "-m", "runtime.cli", "demo", "--no-progress", "--duration", str(duration),
           "--out", out_dir, *demo_args]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(p.stdout), daemon=True)
    reader.start()
    cpu: dict[tuple[str, int, bool], float] = {}
    while p.poll() is None:
        for pid in descendants(p.pid):
            role = _role(pid, p.pid)
            if role is None:
                continue
            try:
                for tid in os.listdir(f"/proc/{pid}/task"):
                    with open(f"/proc/{pid}/task/{tid}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                    key = (role, pid, role == "runtime" and int(tid) == pid)
                    cpu[(*key, int(tid))] = max(cpu.get((*key, int(tid)), 0.0),
                                                (int(fields[11]) + int(fields[12])) / TICK)
            except (OSError, ValueError, IndexError):
                continue
        time.sleep(0.2)
    reader.join()
    shutil.rmtree(out_dir, ignore_errors=True)
    text = "".join(lines)
    m = re.search(r"scans received (\d+)", text)
    if p.returncode != 0 or m is None:
        raise SystemExit(f"the demo failed (exit {p.returncode}):\n{text[-2000:]}")
    roles: dict[str, float] = {}
    for (role, _pid, main_thread, _tid), v in cpu.items():
        if role == "runtime":
            role = "runtime: event loop thread" if main_thread else "runtime: other threads (processing, ...)"
        roles[role] = roles.get(role, 0.0) + v
    return int(m.group(1)), roles


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    demo_args: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, demo_args = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--durations", type=float, nargs=2, default=(10.0, 30.0), metavar=("SHORT", "LONG"),
                    help="emulated seconds of the two runs (default: 10 30)")
    a = ap.parse_args(argv)
    (n0, c0), (n1, c1) = run(a.durations[0], demo_args), run(a.durations[1], demo_args)
    n = n1 - n0
    if n <= 0:
        raise SystemExit("the longer run received no more scans than the shorter one")
    print(f"CPU ms per scan, start-up excluded ({n} scans between a {a.durations[0]:g} s and a "
          f"{a.durations[1]:g} s demo; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores):")
    total = 0.0
    for role in sorted(set(c0) | set(c1)):
        ms = 1e3 * (c1.get(role, 0.0) - c0.get(role, 0.0)) / n
        total += ms
        print(f"  {role:45s} {ms:6.2f}")
    print(f"  {'all':45s} {total:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
