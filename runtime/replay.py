"""Replay: re-run the processing on a recording or a bag, as fast as possible, with other settings.

Two sources for a glassmap recording:
- ``messages``: the decoded /scan and /odom messages (also any ROS 1 / ROS 2 bag with LaserScan plus
  Odometry or /tf, see :mod:`runtime.readers`);
- ``raw``: the raw device bytes, decoded again by the drivers' code (:mod:`runtime.raw_replay`).

Each scan gets the odometry that preceded it in the file, which is what the live run fed the processor
(see :mod:`runtime.pipeline`). With ``as_recorded`` (default for glassmap recordings) only the scans the
live run processed (those with a /pose) are processed, so dropped scans stay dropped and the maps match.
Many files or settings run through :func:`replay_many` (processes on this machine, or a Dask cluster).
The file is read and decoded in the replaying thread, between scans: a reader thread ahead of it took the
interpreter lock in turns with the processing and cost more CPU than it saved (docs/performance.md).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import logging
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from glassmap.types import Odometry, Scan
from runtime.config import RuntimeConfig
from runtime.readers import ReplayInputError, iter_messages, read_metadata, recording_kind
from runtime.recorder import read_mcap
from runtime.parallel import job_executor
from runtime.tuning import freeze_startup, thaw

log = logging.getLogger(__name__)


@dataclass
class ReplayResult:
    """What a replay did. Times in seconds; ``stages``: per-stage time per scan (s)."""

    path: str
    source: str
    scans: int = 0
    skipped: int = 0  # scans the live run dropped (between its first and last processed scans)
    after_end: int = 0  # scans after the live run's last processed scan (it was stopping: never processed)
    odometry: int = 0
    wall_time: float = 0.0
    data_time: float = 0.0  # span of scan stamps in the file
    stages: dict[str, list[float]] = field(default_factory=dict)
    exports: dict[str, str] = field(default_factory=dict)
    error: float | None = None  # classification error against a blueprint, when a world was given
    seen_from: str = ""  # where the scored cells came from: the simulator's record (a file) or the map
    notes: list[str] = field(default_factory=list)  # what the user should know about this replay
    final_pose: tuple[float, float, float] | None = None
    pose_graph: object | None = None  # with mapping.loop_closure: the final runtime.graph_worker.GraphSnapshot
    corrected: object | None = None  # with a world and loop closure: the MapEvaluation of the corrected glass map
    graph_wait: float = 0.0  # s waited after the last scan for the pose graph to catch up and build its final maps

    @property
    def scans_per_second(self) -> float:
        return self.scans / self.wall_time if self.wall_time > 0 else 0.0

    @property
    def speedup(self) -> float:
        """Replay speed relative to real time (data time / wall time)."""
        return self.data_time / self.wall_time if self.wall_time > 0 else 0.0


def scan_key(scan: Scan) -> bytes:
    """Identity of a scan's contents (its ranges as recorded, float32): the same scan decoded from the raw
    bytes and from the /scan message has the same key, whatever the stamps."""
    return hashlib.blake2b(np.asarray(scan.ranges, dtype=np.float32).tobytes(), digest_size=16).digest()


def processed_scans(path: str | Path) -> set[bytes] | None:
    """Keys (:func:`scan_key`) of the scans the live run processed, or None if the recording does not say.

    Each processed scan has a /glass/beams message carrying its ranges, which identifies it by content
    (stamps are not unique: a sensor clock mapping can give two scans the same stamp)."""
    from runtime.messages import scan_from_msg

    keys = {scan_key(scan_from_msg(msg, 0.0)) for _, _, _, msg in read_mcap(path, {"/glass/beams"})}
    return keys or None


def recorded_config(path: str | Path, base: RuntimeConfig | None = None) -> RuntimeConfig:
    """The [mapping] settings the recording was made with (initial pose, laser mount, ...) over ``base``."""
    import json

    cfg = base or RuntimeConfig()
    meta = read_metadata(path) if Path(path).suffix == ".mcap" and Path(path).is_file() else {}
    if "mapping" in meta:
        known = {f.name for f in dataclasses.fields(cfg.mapping)}
        values = {k: v for k, v in json.loads(meta["mapping"]).items() if k in known}
        values.setdefault("registration_sigma", "anchor")  # recorded before the setting: the sigma used then
        values.setdefault("glass_scans", "all")  # recorded before the setting: every scan was registered
        cfg = dataclasses.replace(cfg, mapping=dataclasses.replace(cfg.mapping, **values))
    return cfg


def iter_source(path: str | Path, source: str = "messages") -> Iterator[Scan | Odometry]:
    if source == "messages":
        return iter_messages(path)
    if source == "raw":
        from runtime.raw_replay import iter_raw

        return iter_raw(path)
    raise ValueError(f"source must be 'messages' or 'raw', got {source!r}")


SEEN_FILE = "seen_cells.npy"  # what `glassmap demo` writes beside its recording: the cells the laser saw


def seen_cells_for(path: str | Path, seen: str | Path | None = None) -> Path | None:
    """The seen-cells mask to score a recording with: ``seen`` if given, else the demo's ``seen_cells.npy``
    beside the recording, else None (then the cells the map observed stand in, see runtime.evaluate)."""
    if seen is not None:
        return Path(seen)
    beside = Path(path).parent / SEEN_FILE
    return beside if beside.is_file() else None


def start_pose_note(path: str | Path, config: RuntimeConfig) -> str | None:
    """A note when the replay of ``path`` starts the map at the default pose (0, 0, 0) because the file does
    not record the robot's start pose (a ROS bag; a glassmap recording stores it in its metadata)."""
    p, m = Path(path), config.mapping
    recorded = p.suffix == ".mcap" and p.is_file() and "mapping" in read_metadata(p)
    if recorded or (m.initial_x, m.initial_y, m.initial_yaw) != (0.0, 0.0, 0.0):
        return None
    return ("start pose (0, 0, 0) in the map frame: this file does not record where the robot started; give it "
            "with --mapping.initial_x, --mapping.initial_y (m) and --mapping.initial_yaw (rad)")


def replay_file(path: str | Path, config: RuntimeConfig | None = None, *, source: str = "messages",
                as_recorded: bool = True, out_dir: str | None = None, stem: str = "glass_map",
                progress: bool = True, world: str | None = None, limit: int | None = None,
                seen: str | Path | None = None, live=None) -> ReplayResult:
    """Run the pose estimator and the glass mapper over a recording; export the maps to ``out_dir``.

    world: a simulator world name/path to score the map against its blueprint (simulated recordings), with
    the same rule as the demo; seen: the demo's seen-cells mask (default: ``seen_cells.npy`` beside the
    recording, see :func:`seen_cells_for`). limit: stop after this many scans (>= 1).
    live: a :class:`runtime.live.LiveView` to publish the replay to (as the live run would)."""
    from runtime.processor import MappingProcessor

    if limit is not None and limit < 1:
        raise ValueError(f"limit must be >= 1 scan, got {limit}")
    path = Path(path)
    if recording_kind(path) == "mcap":  # (an unknown kind is said before any progress bar starts)
        from runtime.inputs import check_mcap

        check_mcap(path)  # empty, not MCAP, or cut short: say so (and how to repair) instead of a partial replay
    cfg = config if config is not None else recorded_config(path)
    cfg.validate()
    res = ReplayResult(path=str(path), source=source)
    if (note := start_pose_note(path, cfg)) is not None:
        res.notes.append(note)
    keep: set[bytes] | None = None
    if as_recorded and path.suffix == ".mcap" and path.is_file() and read_metadata(path):
        keep = processed_scans(path)
    proc = MappingProcessor(cfg.mapping)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=f"replay {path.name}", unit="scan", mininterval=0.5)
    pending: list[Odometry] = []
    first = last = None
    unprocessed = 0
    pub = _live_publisher(live, path, cfg) if live is not None else None
    proc.warm_up()  # as the live run does; then start-up objects out of the collector's way (runtime.tuning)
    freeze_startup()
    t0 = time.perf_counter()
    try:
        for item in iter_source(path, source):
            if isinstance(item, Odometry):
                pending.append(item)
                res.odometry += 1
                continue
            if keep is not None and scan_key(item) not in keep:
                unprocessed += 1  # dropped by the live run, or after its end: known at the next kept scan
                continue  # its odometry goes to the next scan
            res.skipped += unprocessed
            unprocessed = 0
            r = proc.process(item, pending)
            if pub is not None:
                pub.publish(pending, r, proc)
            pending = []
            res.scans += 1
            first = item.stamp if first is None else first
            last = item.stamp
            for k, v in r.timings.items():
                res.stages.setdefault(k, []).append(v)
            if bar is not None:
                bar.update(1)
            if limit is not None and res.scans >= limit:
                break
    finally:
        thaw()
        if bar is not None:
            bar.close()
    res.wall_time = time.perf_counter() - t0
    if limit is None or res.scans < limit:
        res.after_end = unprocessed
    if pub is not None and res.scans:
        pub.publish_maps(proc, last)
    if res.scans == 0:
        raise ReplayInputError(f"{path}: no scans were processed")
    res.data_time = float(last - first) if first is not None else 0.0
    est = proc.estimator.estimate()
    res.final_pose = (est.x, est.y, est.yaw)
    t_graph = time.perf_counter()
    res.pose_graph = proc.finish_graph()
    res.graph_wait = time.perf_counter() - t_graph
    if out_dir:
        from runtime.map_worker import export_in_child

        graph = res.pose_graph
        maps, stems = [proc.mapper.copy_maps()], [stem]
        if graph is not None and graph.glass is not None:
            maps.append(graph.glass)
            stems.append(f"{stem}_corrected")
        exported = export_in_child(maps, out_dir, stems)
        res.exports = exported[0]
        if len(exported) > 1:
            res.exports.update({f"corrected_{k}": v for k, v in exported[1].items()})
        elif graph is not None and graph.grid is not None:
            pgm, yaml = graph.grid.save_pgm_yaml(str(Path(out_dir) / f"{stem}_corrected"))
            res.exports.update(corrected_pgm=pgm, corrected_yaml=yaml)
    if world:
        from glassmap.sim.world import load_world
        from runtime.evaluate import evaluate_map

        seen_path = seen_cells_for(path, seen)
        mask = np.load(seen_path) if seen_path is not None else None
        ev = evaluate_map(proc.mapper, load_world(world), seen=mask)
        res.error = ev.error
        if res.pose_graph is not None and res.pose_graph.glass is not None:
            res.corrected = evaluate_map(res.pose_graph.glass, load_world(world), seen=mask)
        res.seen_from = str(seen_path) if ev.seen_from == "simulator" else "map"
    res._processor = proc  # type: ignore[attr-defined]  # for callers in this process (tests)
    return res


def _live_publisher(live, path: Path, cfg: RuntimeConfig):
    from runtime.live import ReplayPublisher
    from runtime.messages import TimeBase

    meta = read_metadata(path) if path.suffix == ".mcap" and path.is_file() else {}
    tb = TimeBase(int(meta.get("time_offset_ns", 0)))
    return ReplayPublisher(live, tb, map_frame=cfg.mapping.map_frame, laser_frame=cfg.laser.laser_frame_id,
                           base_frame=cfg.base.base_link_frame, odom_frame=cfg.base.odom_frame,
                           map_period=cfg.output.live_map_period)


# -- many files / settings ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReplayJob:
    """One replay: a file and the settings to use (picklable, for process pools and Dask)."""

    path: str
    config: RuntimeConfig
    source: str = "messages"
    out_dir: str | None = None
    stem: str = "glass_map"
    world: str | None = None
    seen: str | None = None


def _run_job(job: ReplayJob) -> ReplayResult:
    res = replay_file(job.path, job.config, source=job.source, out_dir=job.out_dir, stem=job.stem,
                      progress=False, world=job.world, seen=job.seen)
    if hasattr(res, "_processor"):
        del res._processor  # type: ignore[attr-defined]  # not picklable cheaply, not needed remotely
    return res


def replay_many(jobs: Iterable[ReplayJob], *, workers: int | None = None, dask_address: str | None = None,
                progress: bool = True) -> list[ReplayResult | BaseException]:
    """Run jobs in parallel: a process pool on this machine (default: one worker per core), or a Dask
    cluster given its scheduler address (``tcp://host:8786``; needs the ``dask`` extra). Results come back
    in job order; a failed job gives its exception instead of a result."""
    jobs = list(jobs)
    results: list[ReplayResult | BaseException] = [None] * len(jobs)  # type: ignore[list-item]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="replay jobs", unit="job")
    try:
        with job_executor(len(jobs), workers, dask_address) as executor:
            futures = {executor.submit(_run_job, j): i for i, j in enumerate(jobs)}
            for fut in concurrent.futures.as_completed(futures):
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except Exception as exc:  # reported per job
                    results[i] = exc
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return results


def with_settings(config: RuntimeConfig, **mapping: object) -> RuntimeConfig:
    """A copy of ``config`` with some [mapping] settings changed (e.g. registration='direct')."""
    return dataclasses.replace(config, mapping=dataclasses.replace(config.mapping, **mapping))


def summarize(results: list[ReplayResult]) -> str:
    lines = []
    for r in results:
        lat = {k: 1e3 * float(np.median(v)) for k, v in r.stages.items()}
        err = ""
        if r.error is not None:
            err = f", error {100 * r.error:.1f} % (per cell, paper rule; " + (
                f"cells seen by the simulated laser from {r.seen_from})" if r.seen_from != "map" else
                "no record of the cells the simulated laser saw: the cells the map observed stand in, so the "
                "figure is not comparable with the demo's; pass --seen out/demo/seen_cells.npy)")
        lines.append(f"{r.path}: {r.scans} scans in {r.wall_time:.1f} s ({r.scans_per_second:.0f} scans/s, "
                     f"{r.speedup:.1f}x real time), median total {lat.get('total', float('nan')):.1f} ms/scan{err}")
        if r.corrected is not None:
            lines.append("  corrected map (key scans at the pose graph's poses): " + r.corrected.describe())
    return "\n".join(lines)
