"""glassmap bench: each run's own peak memory, the machine line, the replay pinned to one core."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest

from runtime.bench import peak_rss_mib, reset_peak_rss


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/clear_refs is Linux only")
def test_the_peak_of_a_later_run_does_not_include_an_earlier_larger_one():
    big = np.ones(80 * 2**20 // 8)  # 80 MiB, touched: resident
    big_peak = peak_rss_mib()
    del big  # a large block goes back to the system at once (mmap)
    assert reset_peak_rss()
    small = np.ones(8 * 2**20 // 8)
    assert peak_rss_mib() < big_peak - 50
    del small


def test_machine_reference_names_the_cpu_and_times_the_workload():
    from runtime.bench import machine_reference

    line = machine_reference()
    m = re.fullmatch(r"machine: (.+), (\d+) cores; reference workload \(3 M Python additions\) (\d+) ms", line)
    assert m and m.group(1) and int(m.group(2)) >= 1 and int(m.group(3)) > 0


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setaffinity"), reason="CPU affinity is Linux only")
def test_pinned_replay_runs_every_scan_on_one_cpu(tmp_path):
    from runtime.bench import pinned_replay
    from tests.runtime.test_bad_input import recording

    got = pinned_replay(recording(tmp_path / "rec.mcap", n=12))
    assert got is not None
    cpu, r = got
    assert r["cpus"] == [cpu] and r["scans"] == 12 and r["rate"] > 0
    assert r["source"] == "messages"  # this recording has no raw bytes
    assert r["reference_ms"] > 0  # the machine's speed on that core at the time of the run


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setaffinity"), reason="CPU affinity is Linux only")
def test_the_one_core_figure_is_the_median_of_the_pinned_runs(tmp_path):
    from runtime.bench import _pinned_line
    from tests.runtime.test_bad_input import recording

    line = _pinned_line(recording(tmp_path / "rec.mcap", n=12), None, 3, "0 busy processes beside it")
    m = re.fullmatch(r"replay from messages, pinned to one core \(CPU \d+; a child process per run, 0 busy processes "
                     r"beside it\): 12 scans, 3 runs: (\d+), (\d+), (\d+) scans/s; median (\d+) scans/s = "
                     r"[\d.]+x real time; reference workload on that core before each run (\d+), (\d+), (\d+) ms",
                     line)
    assert m, line
    rates = sorted(int(g) for g in m.groups()[:3])
    assert int(m.group(4)) == rates[1]
    assert all(int(g) > 0 for g in m.groups()[4:])


def test_live_runs_print_a_line_each_and_how_many_dropped_a_scan():
    from runtime.bench import LiveRun, live_runs_lines

    runs = [LiveRun(2400, 0, 0, 2, 11.0, 95.0, 270.0), LiveRun(2400, 1, 0, 8, 24.0, 140.0, 281.4),
            LiveRun(2399, 0, 2, 3, 13.0, 90.0, 275.0)]
    lines = live_runs_lines(runs, queue_size=8)
    assert lines[1] == ("live run 2 of 3: 2400 scans, dropped 1 (queue full 1, stale 0), most waiting at once 8, "
                        "latency p99 24.00 ms, peak memory 281 MiB; reference workload after it 140 ms")
    assert lines[-1] == ("3 live runs: 2 of 3 dropped a scan (3 scans in all); latency p99 11.00-24.00 ms (median "
                         "13.00); most scans waiting at once 8 (the queue holds 8)")


def test_bench_needs_at_least_one_live_run():
    from runtime.bench import run_bench

    with pytest.raises(ValueError, match="live_runs must be >= 1"):
        run_bench(live_runs=0)


def test_repeated_live_runs_are_summarised_and_the_last_recording_replayed(tmp_path):
    from runtime.bench import run_bench

    report = run_bench(world="room", duration=1.0, out_dir=str(tmp_path), pinned_runs=0, live_runs=2)
    assert re.search(r"^live run 1 of 2: \d+ scans, dropped \d+ ", report, re.M), report
    assert re.search(r"^2 live runs: \d of 2 dropped a scan", report, re.M), report
    assert "the last of 2)" in report and "live runtime (the largest of 2 runs)" in report
    assert (tmp_path / "live-1" / "demo.mcap").is_file() and (tmp_path / "live-2" / "demo.mcap").is_file()
    assert (tmp_path / "replay_raw").is_dir()  # the replays ran on the last recording


def test_a_failed_live_run_in_its_own_process_says_so(tmp_path):
    from runtime.bench import LiveRunError, run_bench

    with pytest.raises(LiveRunError, match="live run 1 of 2 failed in its own process"):
        run_bench(world=str(tmp_path / "no-such-world.toml"), duration=1.0, out_dir=str(tmp_path), pinned_runs=0,
                  live_runs=2)


def test_bench_names_a_bad_world_file_before_it_starts(tmp_path, capsys):
    from runtime.cli import main

    assert main(["bench", "--world", str(tmp_path / "no-such-world.toml"), "--live-runs", "2"]) == 2
    assert "cannot read the world file" in capsys.readouterr().err


def test_bench_refuses_repeated_live_runs_of_a_recording(tmp_path, capsys):
    from runtime.cli import main

    assert main(["bench", "--recording", str(tmp_path / "any.mcap"), "--live-runs", "3"]) == 2
    assert "with --recording there is none" in capsys.readouterr().err
