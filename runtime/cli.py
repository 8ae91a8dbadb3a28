"""The ``glassmap`` command: the root parser and the runtime's own commands (``run``, ``demo``, ``replay``,
``bench``, ``recover``, ``eval``).

The root lives in the runtime, the top layer, because it gathers every part's commands: groups by what they
act on (``sim``, ``glass``, ``pose``, ``hokuyo``, ``pioneer``), each with its own ``register(subparsers)``.
Command modules import heavy dependencies (torch, the simulator) inside their handlers, so that
``glassmap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import os
import sys

import drivers.hokuyo.cli
import drivers.pioneer.cli
import glassmap.glass_cli
import glassmap.pose.cli
import glassmap.sim.cli
from glassmap.cli_help import tidy_help
from glassmap.cli_args import add_no_progress, add_out, add_seed, add_workers, add_world
from glassmap.sim.world import RouteError, WorldFileError
from runtime.config import ConfigError, RuntimeConfig, add_config_flags, config_from_args
from runtime.inputs import InputError
from runtime.output_args import LiveViewError, add_live_arg, add_split_args, apply_split_args, describe_files
from runtime.tuning import setup_process

log = logging.getLogger(__name__)

GROUPS = (glassmap.sim.cli, glassmap.glass_cli, glassmap.pose.cli, drivers.hokuyo.cli, drivers.pioneer.cli)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glassmap",
        description="Online glass confidence maps from a 2D laser rangefinder. The runtime's jobs (run on the "
        "robot, demo against emulated hardware, replay recordings, bench, recover) are top-level commands; the "
        "parts are groups with the same verbs (eval: accuracy, bench: timing, experiment: the paper's "
        "experiment).")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    register(sub)
    for group in GROUPS:
        group_sub = group.register(sub)
        if group is glassmap.glass_cli:
            _register_glass_label(group_sub)
    tidy_help(parser)
    return parser


def _register_glass_label(glass_sub: argparse._SubParsersAction) -> None:
    """``glassmap glass label`` (it reads recordings, so it lives in the runtime layer)."""
    from runtime import label

    p = glass_sub.add_parser("label", help="label a recording's beams from a floor plan (world file)",
                             description="Align each scan of a recording to a floor plan (a world file: walls "
                             "and glass polylines) by scan-to-plan matching from a rough initial pose and the "
                             "odometry, then label every beam glass / not glass / unknown (near segment ends, "
                             "unmatched returns, doubtful alignment). Writes an .npz for `glassmap glass train "
                             "--labelled` and `glassmap glass eval --labelled`.")
    label.add_arguments(p)
    p.set_defaults(func=label.cmd)


def main(argv: list[str] | None = None) -> int:
    setup_process()  # one BLAS thread, one malloc arena, before any thread starts (runtime.tuning)
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except (WorldFileError, RouteError, InputError) as e:  # a world, route, file given on the command line
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into head & co.: stop quietly, like other command-line tools
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run", help="run on the robot: laser + base -> maps online, MCAP recording",
        description="Connect to the Hokuyo and the Pioneer, estimate the pose, build the occupancy and glass "
        "confidence maps online and write them (PNG, .npy, PGM + YAML) every output.export_period s and at "
        "exit. The robot never moves unless --teleop is given (keyboard). Ctrl-C or SIGTERM stops cleanly: "
        "robot stopped and disabled, laser stopped, recording finished.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--laser", metavar="URL", help="laser URL (default from [laser]: tcp://192.168.0.10:10940)")
    p.add_argument("--base", metavar="URL", help="base URL (default from [base]: serial:///dev/ttyUSB0?baud=9600; "
                   "'none' = no base: mapping from scan matching alone)")
    p.add_argument("--record", metavar="FILE", help="record everything to this MCAP file (= output.record; "
                   "its directory must exist)")
    p.add_argument("--out", metavar="DIR", help="map output directory (= output.out_dir)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--teleop", action="store_true", help="drive with the keyboard (enables the motors)")
    add_split_args(p)
    add_live_arg(p)
    add_config_flags(p)
    p.set_defaults(func=cmd_run)

    d = sub.add_parser(
        "demo", help="the full runtime against emulated hardware in the simulated office",
        description="Start an emulated Hokuyo (loopback TCP) and an emulated Pioneer (pseudo-terminal) driven "
        "by the simulator, connect the runtime to them as to hardware, drive the world's route with velocity "
        "commands, build the maps online, then write the glass confidence map PNG and the MCAP recording and "
        "print the classification error against the blueprint.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_world(d)
    d.add_argument("--route", default=None, help="route of the world (default: its default route)")
    d.add_argument("--speed", type=float, default=1.0, help="run the emulated devices this many times faster "
                   "than real time (scans come at 40 x speed Hz; scans the processing cannot keep up with are "
                   "dropped and counted)")
    d.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S emulated seconds (default: when the route is done)")
    add_out(d, "out/demo", "output directory (maps, demo.mcap)")
    d.add_argument("--no-record", action="store_true", help="do not write the MCAP recording")
    add_seed(d, what="seed of the simulated robot and laser noise")
    d.add_argument("--registration", choices=("direct", "robust"), default=None,
                   help="glass registration (default: mapping.registration, robust)")
    d.add_argument("--window", type=int, choices=(3, 5), default=None,
                   help="robust registration window k (default: mapping.window, 3)")
    add_no_progress(d)
    add_split_args(d)
    add_live_arg(d)
    add_config_flags(d)
    d.set_defaults(func=cmd_demo)

    r = sub.add_parser(
        "replay", help="re-run the mapping on recordings or ROS bags, as fast as possible",
        description="Re-run pose estimation and glass mapping on a glassmap MCAP recording (from the decoded "
        "messages or from the raw device bytes through the drivers' decoders), or on ROS 1 (.bag) / ROS 2 "
        "(directory, .mcap, .db3) bags with sensor_msgs/LaserScan plus nav_msgs/Odometry or /tf. Settings "
        "default to those the recording was made with; change them with the flags (e.g. "
        "--mapping.registration direct). Several files run in parallel (processes, or a Dask cluster).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    r.add_argument("files", nargs="+", metavar="FILE", help="recordings or bags")
    r.add_argument("--source", choices=("messages", "raw"), default="messages",
                   help="decoded /scan + /odom messages, or the raw device bytes (glassmap recordings only)")
    add_out(r, "out/replay", "output directory (one map set per file)")
    r.add_argument("--all-scans", action="store_true", help="process every scan, also those the live run "
                   "dropped (default: only the scans the live run processed, so the maps can match)")
    add_world(r, None, "score the map against this simulator world's blueprint, with the demo's rule (the "
              "cells the simulated laser saw, see --seen)")
    r.add_argument("--seen", default=None, metavar="FILE", help="the demo's record of the cells the simulated "
                   "laser saw (default: seen_cells.npy beside the recording; without it the cells the map "
                   "observed stand in, which scores differently)")
    r.add_argument("--limit", type=int, default=None, metavar="N", help="stop after N scans, N >= 1 (a quick look)")
    add_workers(r, "parallel processes for several files")
    r.add_argument("--dask", metavar="ADDRESS", default=None, help="run on a Dask cluster (scheduler address, "
                   "e.g. tcp://10.0.0.2:8786; needs pip install 'glassmap[dask]')")
    add_no_progress(r)
    add_live_arg(r)
    add_config_flags(r)
    r.set_defaults(func=cmd_replay)

    b = sub.add_parser(
        "bench", help="runtime figures: per-stage time, replay throughput, latency p50/p99, peak memory",
        description="Record a live run against the emulated devices at real time (40 Hz), measuring the "
        "latency from the scan's bytes arriving to the maps updated; then replay the recording as fast as "
        "possible from the messages and from the raw bytes. Prints per-stage time per scan, throughput "
        "(scans/s and x real time), latency p50/p99 and peak memory.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_world(b)
    b.add_argument("--duration", type=float, default=20.0, help="emulated seconds of the live run")
    b.add_argument("--recording", default=None, help="replay this recording instead of recording a new one "
                   "(no live latency figures then)")
    b.add_argument("--load", type=_non_negative_int, default=0, metavar="N",
                   help="run N CPU-bound processes beside the benchmark (the figures then say so): loaded figures "
                   "that anyone can reproduce")
    b.add_argument("--stages", action="store_true", help="also replay the recording once more with every stage of "
                   "the processing timed (CPU time of the thread: holds on a busy machine) and print the table")
    b.add_argument("--live-runs", type=_positive_int, default=1, metavar="N",
                   help="repeat the live run N times (a scan dropped now and then under --load shows only over many "
                   "runs): a line per run and a summary; the replays use the last run's recording (in OUT/live-N)")
    b.add_argument("--pinned-runs", type=_non_negative_int, default=3, metavar="N",
                   help="replays of the raw bytes pinned to one core (Linux), each in its own process; the median "
                   "is the one-core figure (0: none)")
    add_out(b, "out/bench")
    add_config_flags(b)
    b.set_defaults(func=cmd_bench)

    e = sub.add_parser(
        "eval", help="generalisation benchmark: the pipeline on generated test worlds + the built-in ones",
        description="Run the classifier, the glass map with true poses, the paper's experiment (direct vs robust "
        "3x3 / 5x5 under pose error), the pose estimator and the runtime demo on generated test worlds (seeds "
        "0-99, never used for training or tuning) and the built-in worlds; report per world and aggregated "
        "(mean and worst world) to CSV, JSON and a figure.")
    from runtime.benchmark import add_arguments, cmd as cmd_benchmark

    add_arguments(e)
    e.set_defaults(func=cmd_benchmark)

    c = sub.add_parser(
        "recover", help="repair an MCAP recording cut short by a crash (adds index and footer)",
        description="A recording interrupted by a crash or SIGKILL holds every completed chunk but no "
        "footer; this rewrites it into a complete file that Foxglove and rosbags open.")
    c.add_argument("src", help="the cut-short .mcap")
    c.add_argument("dst", help="the repaired .mcap to write")
    c.set_defaults(func=cmd_recover)


def _config(args, base: RuntimeConfig | None = None) -> RuntimeConfig:
    try:
        cfg = config_from_args(args, base)
        if getattr(args, "live", None):
            cfg.output.live = args.live
        apply_split_args(args, cfg.output)
        cfg.validate()
        return cfg
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def cmd_run(args) -> int:
    from drivers.errors import DriverError
    from runtime.app import Runtime, RuntimeFailure

    cfg = _config(args)
    if args.laser:
        cfg.laser_url = args.laser
    if args.base:
        cfg.base_url = "none" if args.base.lower() == "none" else args.base
    if args.record:
        cfg.output.record = args.record
    if args.out:
        cfg.output.out_dir = args.out
    if (rc := _check_run_inputs(cfg)) != 0:
        return rc
    driver = None
    if args.teleop:
        from runtime.teleop import keyboard_driver

        cfg.base.enable_motors = True
        driver = keyboard_driver(cfg.base.max_v, cfg.base.max_omega)
    rt = Runtime(cfg, driver=driver)
    try:
        summary = asyncio.run(rt.run(duration=args.duration))
    except (DriverError, RuntimeFailure, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        if exc.__cause__ is not None:
            print(f"  cause: {exc.__cause__}", file=sys.stderr)
        return 1
    print(f"stopped: {summary.stop_reason}; {summary.stages.summary()}")
    for k, v in summary.exports.items():
        print(f"map {k}: {v}")
    if summary.recording:
        stopped = "; stopped early, see the error above" if summary.recording_error else ""
        print(f"recording: {describe_files(summary.recording_files) or summary.recording} "
              f"({summary.recorded_messages} messages{stopped})")
    if summary.live:
        print(f"live view: {summary.live} ({summary.live_sent} messages sent, {summary.live_dropped} dropped)")
    return 0


def _check_run_inputs(cfg: RuntimeConfig) -> int:
    """Device URLs and the recording path checked before anything is opened or loaded; 2 (with one line on
    stderr) if one is unusable."""
    from drivers.errors import InvalidURL
    from runtime.inputs import check_device_url, check_output_file

    try:
        check_device_url(cfg.resolved_laser_url(), "laser")
        check_device_url(cfg.resolved_base_url(), "base", optional=True)
        if cfg.output.record:
            check_output_file(cfg.output.record, "recording")
    except (InvalidURL, InputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def cmd_demo(args) -> int:
    from runtime.demo import DemoOptions, format_result, run_demo

    cfg = _config(args)
    opts = DemoOptions(world=args.world, route=args.route, speed=args.speed, duration=args.duration,
                       out_dir=args.out, record=not args.no_record, seed=args.seed,
                       registration=args.registration, window=args.window, progress=not args.no_progress,
                       config=cfg)
    if not (opts.speed > 0 and math.isfinite(opts.speed)):
        print("error: --speed must be > 0", file=sys.stderr)
        return 2
    from drivers.errors import DriverError
    from runtime.app import RuntimeFailure

    try:
        res = asyncio.run(run_demo(opts))
    except (ValueError, DriverError, RuntimeFailure, RuntimeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        if exc.__cause__ is not None:
            print(f"  cause: {exc.__cause__}", file=sys.stderr)
        return 1
    print(format_result(res))
    return 0


def cmd_replay(args) -> int:
    from runtime.readers import ReplayInputError
    from runtime.replay import ReplayJob, recorded_config, replay_file, replay_many, summarize

    if args.limit is not None and args.limit < 1:
        print(f"error: --limit must be >= 1, got {args.limit}", file=sys.stderr)
        return 2
    jobs = []
    for i, f in enumerate(args.files):
        cfg = _config(args, base=recorded_config(f))
        stem = "glass_map" if len(args.files) == 1 else f"glass_map_{i:03d}"
        jobs.append(ReplayJob(path=f, config=cfg, source=args.source, out_dir=args.out, stem=stem,
                              world=args.world, seen=args.seen))
    if args.live and (len(jobs) > 1 or args.dask):
        print("error: --live shows one replay: give one file (and no --dask)", file=sys.stderr)
        return 2
    if len(jobs) == 1 and not args.dask:
        j = jobs[0]
        live = None
        try:
            if args.live:
                from runtime.live import start_live_view

                live = start_live_view(j.config.output)
                print(f"live view: {live.url} (Foxglove: Open connection -> Foxglove WebSocket URL)",
                      file=sys.stderr, flush=True)
            res = replay_file(j.path, j.config, source=j.source, out_dir=j.out_dir, stem=j.stem,
                              progress=not args.no_progress, world=j.world, as_recorded=not args.all_scans,
                              limit=args.limit, seen=j.seen, live=live)
        except (ReplayInputError, ValueError, LiveViewError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        finally:
            if live is not None:
                live.close()
        print(summarize([res]))
        for note in res.notes:
            print(f"note: {note}")
        if res.skipped:
            print(f"{res.skipped} scans skipped: the live run dropped them (--all-scans processes them too)")
        if res.after_end:
            print(f"{res.after_end} scans after the live run's last processed scan (it was stopping) not processed")
        for k, v in res.exports.items():
            print(f"map {k}: {v}")
        return 0
    results = replay_many(jobs, workers=args.workers or None, dask_address=args.dask, progress=not args.no_progress)
    ok = [r for r in results if not isinstance(r, BaseException)]
    print(summarize(ok))
    failed = 0
    for j, r in zip(jobs, results):
        if isinstance(r, BaseException):
            failed += 1
            print(f"{j.path}: failed: {r}", file=sys.stderr)
    return 1 if failed else 0


def _int_at_least(minimum: int):
    """An argparse type: a whole number >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {n}")
        return n

    return parse


_non_negative_int = _int_at_least(0)
_positive_int = _int_at_least(1)


def cmd_bench(args) -> int:
    from runtime.bench import LiveRunError, run_bench

    base = None
    if args.recording is not None:  # its recorded settings, then the flags
        if args.live_runs > 1:
            print("error: --live-runs repeats the live run, and with --recording there is none", file=sys.stderr)
            return 2
        from runtime.replay import recorded_config

        base = recorded_config(args.recording)
    else:  # a bad world file is said before anything starts
        from glassmap.sim.world import WorldFileError, load_world

        try:
            load_world(args.world)
        except WorldFileError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    try:
        print(run_bench(world=args.world, duration=args.duration, recording=args.recording, out_dir=args.out,
                        load=args.load, stages=args.stages, config=_config(args, base), pinned_runs=args.pinned_runs,
                        live_runs=args.live_runs))
    except LiveRunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def cmd_recover(args) -> int:
    from runtime.inputs import recover_recording

    rep = recover_recording(args.src, args.dst)  # an InputError is main's one-line error
    print(f"{args.dst}: {rep.messages} messages recovered")
    for t, n in sorted(rep.topics.items()):
        print(f"  {t}: {n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
