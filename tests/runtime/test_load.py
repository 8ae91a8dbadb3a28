"""The busy processes of ``glassmap bench --load N``."""

import os
import time

import pytest

from runtime.cli import build_parser
from runtime.load import BusyProcesses, LoadError


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (s) from /proc."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs /proc to read a process's CPU time")
def test_busy_processes_burn_cpu_and_end_with_the_block():
    with BusyProcesses(1) as busy:
        assert busy.running == 1
        pid = busy.procs[0].pid
        time.sleep(0.6)
        assert _cpu_seconds(pid) > 0.2  # spinning, not sleeping
        procs = list(busy.procs)
    assert all(p.poll() is not None for p in procs)
    assert busy.running == 0


def test_zero_busy_processes_start_nothing():
    with BusyProcesses(0) as busy:
        assert busy.procs == []


def test_negative_load_is_refused():
    with pytest.raises(LoadError):
        BusyProcesses(-1)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "--load", "-1"])
    assert build_parser().parse_args(["bench", "--load", "2"]).load == 2
