"""``glassmap bench``: per-stage time per scan, replay throughput, live latency (p50, p99), peak memory.

1. Live: the runtime against the emulated devices (separate process) at real time, 40 Hz, recording to
   MCAP: latency from the scan's last bytes arriving (transport read) to the maps updated, per scan.
2. Replay of that recording as fast as possible, from the decoded messages and from the raw bytes through
   the drivers' decoders: scans/s, times real time, per-stage time per scan; and the raw replay again in
   processes pinned to one core (Linux, :func:`pinned_replay`; ``pinned_runs`` of them, their median): the
   target's "on one core", literally.
3. Peak resident memory: of the live runtime, of each replay (each run's own peak: the kernel's high-water
   mark is reset between the runs, :func:`reset_peak_rss`), of this whole process (the three runs one after
   the other) and of the largest child process (emulated devices, map worker).
``live_runs`` > 1 repeats the live run (a scan dropped now and then under load shows only over many runs),
each but the last in a process of its own: one line per run and a summary; the replays use the last
run's recording.
``stages``: also the CPU time of each stage of the processing (:mod:`runtime.stageprof`).
``load`` > 0 runs that many CPU-bound processes (:mod:`runtime.load`) beside all of it; every figure printed
says how many. ``config``: the runtime's settings (``--config``, ``--mapping.*`` ... flags), e.g.
``mapping.loop_closure``: the pose graph's worker process then runs beside the scans, and each replay also
says how long the run waited after its last scan for the graph to catch up (counted in a second throughput
figure).
Targets on the development machine (issue 19): replay from raw bytes >= 400 scans/s on one core, live p99
latency <= 20 ms idle and <= 25 ms with one busy process (``--load 1``), no scan dropped at 40 Hz, runtime
peak memory <= 300 MiB (docs/performance.md).
The per-stage medians are over all scans: scan matching and the occupancy update run on key scans only
(motion filter, ``mapping.keyframe_*``), so their p90 / p99 show the cost of a key scan.
"""

from __future__ import annotations

import asyncio
import os
import resource
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def _ms(v) -> str:
    a = np.asarray(v, dtype=float) * 1e3
    if a.size == 0:
        return "n/a"
    return f"median {np.median(a):6.2f}  p90 {np.percentile(a, 90):6.2f}  p99 {np.percentile(a, 99):6.2f}  ms"


def machine_reference() -> str:
    """The CPU model and the time of a fixed pure-Python workload (3 million additions, best of three), so
    that figures from different machines can be compared."""
    import platform

    model = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model)
    except OSError:
        pass
    return (f"machine: {model}, {os.cpu_count()} cores; reference workload (3 M Python additions) "
            f"{reference_workload_ms():.0f} ms")


def reference_workload_ms() -> float:
    """Time (ms) of a fixed pure-Python workload (3 million additions, best of three) on this process's CPUs
    now: the machine's speed at the time of a measurement (a virtual machine's speed can drift by half
    within minutes)."""
    import time

    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        s = 0
        for i in range(3_000_000):
            s += i
        best = min(best, time.perf_counter() - t)
    return 1e3 * best


def reset_peak_rss() -> bool:
    """Reset this process's peak resident set (VmHWM) to its current size (Linux >= 4.0,
    /proc/self/clear_refs); False where that is not possible (the peaks then include the earlier runs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mib() -> float:
    """This process's peak resident set (MiB) since the start or the last :func:`reset_peak_rss`."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


_PINNED_CHILD = """
import json, os, pickle, sys
from runtime.tuning import setup_process
setup_process()  # as the glassmap program does
from runtime.bench import reference_workload_ms
from runtime.readers import ReplayInputError
from runtime.replay import replay_file
config = pickle.load(sys.stdin.buffer)
reference_ms = reference_workload_ms()  # the machine's speed on this core, just before this run
try:
    source, r = "raw", replay_file(sys.argv[1], config, source="raw", progress=False, as_recorded=False)
except ReplayInputError:  # recorded without the raw bytes
    source, r = "messages", replay_file(sys.argv[1], config, progress=False, as_recorded=False)
print("PINNED " + json.dumps({"source": source, "scans": r.scans, "wall": r.wall_time, "rate": r.scans_per_second,
                               "speedup": r.speedup, "cpus": sorted(os.sched_getaffinity(0)),
                               "reference_ms": reference_ms}))
"""


def _checkout_env(root: str | Path | None = None) -> tuple[str, dict[str, str]]:
    """The checkout ``root`` (default: this one) and an environment whose Python imports its code first."""
    root = str(Path(root).resolve() if root is not None else Path(__file__).resolve().parents[1])
    return root, {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}


class PinnedReplayError(RuntimeError):
    """The pinned replay's child process failed (its error output is in the message)."""


def pinned_replay(recording: str | Path, config=None, root: str | Path | None = None) -> tuple[int, dict] | None:
    """Replay ``recording``'s raw bytes (its messages if it has none) with ``config`` (None: the recording's
    settings) in a child process pinned to one CPU (the last this process may use; every thread of the child
    runs on it), with the code of the checkout ``root`` (default: this one): (cpu, {source, scans, wall, rate,
    speedup, cpus}); ``cpus``: the CPUs the child could run on at its end. None where affinity cannot be set
    (not Linux); :class:`PinnedReplayError` if the child fails."""
    import json
    import pickle
    import subprocess
    import sys

    if not hasattr(os, "sched_setaffinity"):
        return None
    cpu = max(os.sched_getaffinity(0))
    root, env = _checkout_env(root)
    out = subprocess.run([sys.executable, "-c", _PINNED_CHILD, str(Path(recording).resolve())],
                         input=pickle.dumps(config), capture_output=True, env=env, cwd=root,
                         preexec_fn=lambda: os.sched_setaffinity(0, {cpu}))
    for line in out.stdout.decode(errors="replace").splitlines():
        if line.startswith("PINNED "):
            return cpu, json.loads(line[7:])
    raise PinnedReplayError(f"the replay of {recording} pinned to CPU {cpu} failed (exit {out.returncode}): "
                            + out.stderr.decode(errors="replace")[-1500:])


def _pinned_line(recording: str | Path, config, runs: int, beside: str) -> str:
    """``runs`` replays pinned to one core, as one line: each run's rate and their median (the machine's
    speed drifts from minute to minute: one short run is a sample, not the figure)."""
    rates, refs, p, cpu = [], [], None, None
    for _ in range(runs):
        try:
            got = pinned_replay(recording, config)
        except PinnedReplayError as exc:  # the other figures stand: say so rather than lose them
            return f"replay pinned to one core: {exc}"
        if got is None:
            return "replay pinned to one core: not possible here (no CPU affinity on this system)"
        cpu, p = got
        rates.append(p["rate"])
        refs.append(p["reference_ms"])
    med = float(np.median(rates))
    return (f"replay from {p['source']}, pinned to one core (CPU {cpu}; a child process per run, {beside}): "
            f"{p['scans']} scans, {runs} run{'s' if runs != 1 else ''}: {', '.join(f'{r:.0f}' for r in rates)} "
            f"scans/s; median {med:.0f} scans/s = {med * p['speedup'] / p['rate']:.1f}x real time; reference "
            f"workload on that core before each run {', '.join(f'{r:.0f}' for r in refs)} ms")


@dataclass
class LiveRun:
    """The figures of one live run (``glassmap bench --live-runs N``)."""

    scans: int  # scans received
    dropped_overflow: int  # dropped because the processing queue was full
    dropped_stale: int  # dropped because they were older than pipeline.max_scan_age
    most_waiting: int  # the most scans waiting for processing at once
    p99_ms: float  # latency, scan bytes in -> maps updated
    reference_ms: float  # the machine's speed just after the run (reference_workload_ms)
    peak_mib: float  # the runtime's peak resident memory (MiB)

    @property
    def dropped(self) -> int:
        return self.dropped_overflow + self.dropped_stale


def live_runs_lines(runs: list[LiveRun], queue_size: int) -> list[str]:
    """One line per live run, then a summary over the runs: how many dropped a scan, the p99 range."""
    n = len(runs)
    lines = [f"live run {i} of {n}: {r.scans} scans, dropped {r.dropped} (queue full {r.dropped_overflow}, stale "
             f"{r.dropped_stale}), most waiting at once {r.most_waiting}, latency p99 {r.p99_ms:.2f} ms, peak memory "
             f"{r.peak_mib:.0f} MiB; reference workload after it {r.reference_ms:.0f} ms"
             for i, r in enumerate(runs, 1)]
    p99 = [r.p99_ms for r in runs]
    with_drops = sum(r.dropped > 0 for r in runs)
    lines.append(f"{n} live runs: {with_drops} of {n} dropped a scan ({sum(r.dropped for r in runs)} scans in all); "
                 f"latency p99 {min(p99):.2f}-{max(p99):.2f} ms (median {float(np.median(p99)):.2f}); most scans "
                 f"waiting at once {max(r.most_waiting for r in runs)} (the queue holds {queue_size})")
    return lines


def _live_figures(res, peak_mib: float) -> LiveRun:
    """The :class:`LiveRun` of a demo result (``runtime.demo.DemoResult``), timing the machine now."""
    st = res.summary.stages
    p99 = float(np.percentile(np.asarray(res.latency) * 1e3, 99)) if res.latency else float("nan")
    return LiveRun(st.scans_received, st.dropped_overflow, st.dropped_stale, st.most_waiting, p99,
                   reference_workload_ms(), peak_mib)


_LIVE_CHILD = """
import asyncio, dataclasses, json, pickle, sys
from runtime.tuning import setup_process
setup_process()  # as the glassmap program does
from runtime.bench import _live_figures, peak_rss_mib
from runtime.demo import DemoOptions, run_demo
config = pickle.load(sys.stdin.buffer)
res = asyncio.run(run_demo(DemoOptions(world=sys.argv[1], speed=1.0, duration=float(sys.argv[2]), out_dir=sys.argv[3],
                                       progress=True, config=config)))
print("LIVE " + json.dumps(dataclasses.asdict(_live_figures(res, peak_rss_mib()))))
"""


class LiveRunError(RuntimeError):
    """A live run in its own process failed."""


def _live_run_in_child(world: str, duration: float, out: Path, config, i: int, n: int) -> LiveRun:
    """Live run ``i`` of ``n`` in a child process (this checkout's code), recording to ``out``; its progress
    and errors go to this process's stderr. :class:`LiveRunError` if it fails."""
    import json
    import pickle
    import subprocess
    import sys

    _, env = _checkout_env()
    if Path(world).is_file():
        world = str(Path(world).resolve())
    print(f"live run {i} of {n} (its own process)", file=sys.stderr, flush=True)
    got = subprocess.run([sys.executable, "-c", _LIVE_CHILD, world, str(duration), str(out.resolve())],
                         input=pickle.dumps(config), stdout=subprocess.PIPE, env=env)
    for line in got.stdout.decode(errors="replace").splitlines():
        if line.startswith("LIVE "):
            return LiveRun(**json.loads(line[5:]))
    raise LiveRunError(f"live run {i} of {n} failed in its own process (exit {got.returncode}); its error output is "
                       "above")


STARTUP_S = 2.0  # seconds of scans at 40 Hz reported separately as start-up

STAGES = (("pose", "pose (prediction + matching + fusion)"), ("likelihood_field", "likelihood field rebuild or update"),
          ("occupancy", "occupancy update (estimator)"), ("glass", "glass path (+ occupancy update by the mapper)"),
          ("total", "total (wall clock)"), ("cpu", "total (CPU time of the thread)"))


def _stage_lines(stages: dict, prefix: str) -> list[str]:
    out = []
    for key, label in STAGES:
        v = stages.get(key)
        if v is None or not np.any(np.asarray(v)):
            continue
        out.append(f"  {prefix}{label:46s} {_ms(v)}")
    return out


def run_bench(world: str = "office", duration: float = 20.0, recording: str | None = None,
              out_dir: str = "out/bench", load: int = 0, stages: bool = False, config=None,
              pinned_runs: int = 3, live_runs: int = 1) -> str:
    """config: a :class:`runtime.config.RuntimeConfig` for the live run and, with ``recording``, its replays
    (default: the defaults; a recording made here is replayed with its recorded settings). pinned_runs:
    replays pinned to one core (their median is the figure; 0: none). live_runs: live runs (>= 1; ignored with
    ``recording``), each recorded in ``out_dir``/live-N when more than one."""
    from runtime.load import BusyProcesses

    if live_runs < 1:
        raise ValueError(f"live_runs must be >= 1, got {live_runs}")
    with BusyProcesses(load) as busy:
        lines = _run(world, duration, recording, out_dir, f"{load} busy process{'es' if load != 1 else ''} beside it",
                     stages, config, pinned_runs, live_runs)
        if busy.running != load:
            lines.append(f"warning: only {busy.running} of the {load} busy processes were still running at the end")
    return "\n".join(lines)


def _run(world: str, duration: float, recording: str | None, out_dir: str, beside: str, stages: bool,
         config=None, pinned_runs: int = 3, live_runs: int = 1) -> list[str]:
    from runtime.config import PipelineConfig
    from runtime.replay import replay_file
    from runtime.tuning import release_memory

    lc = config is not None and config.mapping.loop_closure
    pipeline = config.pipeline if config is not None else PipelineConfig()
    lines = [machine_reference() + f" ({beside})",
             f"load: {beside} (glassmap bench --load N); loop closure {'on' if lc else 'off'} "
             f"(--mapping.loop_closure); processing thread niceness {pipeline.nice} (--pipeline.nice)"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    replay_config = config
    peaks: dict[str, float] = {}  # each run's own peak resident set (MiB)
    separate = reset_peak_rss()
    if recording is None:
        from runtime.demo import DemoOptions, run_demo

        replay_config = None  # the recording's own settings (start pose, loop closure, ...)
        # every run but the last in a process of its own, as a fresh `glassmap bench` would run it (later runs
        # in one process are not alike: more scans waiting, a higher peak); the last one here, for its details
        runs = [_live_run_in_child(world, duration, out / f"live-{i}", config, i, live_runs)
                for i in range(1, live_runs)]
        separate = separate and reset_peak_rss()
        res = asyncio.run(run_demo(DemoOptions(world=world, speed=1.0, duration=duration,
                                               out_dir=str(out if live_runs == 1 else out / f"live-{live_runs}"),
                                               progress=True, config=config)))
        runs.append(_live_figures(res, peak_rss_mib()))
        if live_runs > 1:
            lines += live_runs_lines(runs, pipeline.queue_size)
        s = res.summary
        recording = res.recording
        last = f", the last of {live_runs}" if live_runs > 1 else ""
        lines.append(f"live run ({world}, {duration:g} s at 40 Hz, real time, {beside}{last}): {s.stages.summary()}")
        lines.append(f"  latency scan bytes in -> maps updated: {_ms(res.latency)}")
        lines.append(f"  most scans waiting for processing at once: {s.stages.most_waiting} "
                     f"(the queue holds {pipeline.queue_size}: --pipeline.queue_size)")
        skip = int(round(STARTUP_S * 40))
        if len(res.latency) > 2 * skip:
            lines.append(f"  the same after the first {STARTUP_S:g} s (start-up: first likelihood fields, map "
                         f"growth):  {_ms(res.latency[skip:])}")
        lines += _stage_lines(res.stages, "live: ")
        lines.append(f"  machine speed at the end of the live run: reference workload {runs[-1].reference_ms:.0f} ms "
                     "(at its start: the first line)")
        peaks["live runtime" if live_runs == 1 else f"live runtime (the largest of {live_runs} runs)"] = max(
            r.peak_mib for r in runs)
        release_memory()
    for source in ("messages", "raw"):
        separate = separate and reset_peak_rss()
        r = replay_file(recording, replay_config, source=source, out_dir=str(out / f"replay_{source}"), progress=True,
                        as_recorded=False)
        lines.append(f"replay from {source} ({beside}): {r.scans} scans in {r.wall_time:.2f} s = "
                     f"{r.scans_per_second:.0f} scans/s = {r.speedup:.1f}x real time")
        if r.pose_graph is not None:
            graph = r._processor.graph  # type: ignore[attr-defined]
            total = r.wall_time + r.graph_wait
            lines.append(f"  pose graph ({'a thread' if graph.in_process else 'its own process'}): "
                         f"{len(r.pose_graph.stamps)} key scans, {r.pose_graph.closures} loop closures, busy "
                         f"{graph.busy_time:.2f} s; waited {r.graph_wait:.2f} s after the last scan for it to catch "
                         f"up and build the final corrected maps ({graph.map_seconds:.2f} s of it): "
                         f"{r.data_time / total:.1f}x real time with the wait")
        lines += _stage_lines(r.stages, "")
        peaks[f"replay from {source}"] = peak_rss_mib()
        del r  # its processor (grids, likelihood fields, reference cycles) is gone before the next run starts
        release_memory()
    if pinned_runs > 0:
        lines.append(_pinned_line(recording, replay_config, pinned_runs, beside))
    if stages:
        from runtime.stageprof import stage_profile

        from runtime.readers import ReplayInputError

        try:  # the raw bytes (the target path) when recorded
            source, t = "raw bytes", stage_profile(str(recording), "raw")
        except ReplayInputError:
            source, t = "messages", stage_profile(str(recording))
        lines.append(f"CPU time per stage, replay of the {source} ({t.scans} scans, {beside}; runtime/stageprof.py):")
        lines.append(t.table())
    # ru_maxrss is the high-water mark since the last reset: the whole process's peak is the largest run's
    own = max([resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, *peaks.values()])
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    if separate:
        lines.append("peak memory (resident, each run's own): "
                     + ", ".join(f"{k} {v:.0f}" for k, v in peaks.items()) + " MiB")
    lines.append(f"peak memory: this process (all its runs) {own:.0f} MiB; largest child process (emulated "
                 f"devices, map worker, the replays' map export; a child started late counts this process's "
                 f"resident set at its fork) {kids:.0f} MiB")
    lines.append("targets (issue 19): replay from raw >= 400 scans/s (10x real time) on one core (pinned); live p99 "
                 "<= 20 ms idle, <= 25 ms with one busy process (--load 1), no scan dropped at 40 Hz; runtime peak "
                 "memory <= 300 MiB")
    try:
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        lines.append(f"machine load average (1, 5, 15 min): {load} on {os.cpu_count()} cores (other work slows "
                     "every figure above)")
    except OSError:
        pass
    return lines
