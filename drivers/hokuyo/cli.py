"""``glassmap hokuyo ...``: probe, stream, record, emulate and benchmark a Hokuyo SCIP 2.0 laser."""

from __future__ import annotations

import argparse
import asyncio
import sys
import time

from glassmap.cli_args import add_world

DEFAULT_URL = "tcp://192.168.0.10:10940"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "hokuyo", help="Hokuyo UTM-30LX-EW laser: probe, stream, record, emulate, benchmark",
        description="Talk to a Hokuyo SCIP 2.0 laser (UTM-30LX-EW over tcp://HOST:PORT, USB models over "
        "serial:///dev/ttyACM0), run the emulator, or benchmark the decoder.")
    sub = p.add_subparsers(dest="hokuyo_command", required=True, metavar="ACTION")

    probe = sub.add_parser("probe", help="print the sensor's VV, PP and II replies",
                           description="Connect, stop any stream, and print version (VV), parameters (PP) "
                           "and status (II).")
    probe.add_argument("url", nargs="?", default=DEFAULT_URL, help=f"sensor URL (default {DEFAULT_URL})")
    probe.set_defaults(func=_probe)

    stream = sub.add_parser("stream", help="stream N scans and print the rate and error counters",
                            description="Stream scans (ME: distance + intensity) and report scans/s and the "
                            "client's counters (received, corrupted, dropped, reconnects, ...).")
    stream.add_argument("url", nargs="?", default=DEFAULT_URL, help=f"sensor URL (default {DEFAULT_URL})")
    stream.add_argument("-n", "--scans", type=int, default=200, help="scans to take (default 200)")
    _stream_options(stream)
    stream.set_defaults(func=_stream)

    rec = sub.add_parser("record", help="record the raw bytes of a session for later replay",
                         description="Stream N scans and save every byte both ways, with host timestamps, "
                         "to a capture file (.jsonl) that tests/fakes/replay.py can play back as the sensor.")
    rec.add_argument("url", help="sensor URL, e.g. tcp://192.168.0.10:10940")
    rec.add_argument("file", help="output capture file (.jsonl)")
    rec.add_argument("-n", "--scans", type=int, default=100, help="scans to record (default 100)")
    rec.add_argument("--note", default="", help="free text stored in the capture header")
    _stream_options(rec)
    rec.set_defaults(func=_record)

    emu = sub.add_parser("emulate", help="run the UTM-30LX-EW emulator on loopback TCP or a pty",
                         description="Serve an emulated UTM-30LX-EW until Ctrl-C (or --duration). Scans come "
                         "from a simulated world (--world) or a synthetic rectangular room.")
    emu.add_argument("--port", type=int, default=10940, help="TCP port on 127.0.0.1 (default 10940; 0 = any)")
    emu.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal instead of TCP")
    add_world(emu, None, "simulated world, the laser at its start pose (none: a synthetic room)")
    emu.add_argument("--time-scale", type=float, default=1.0, help="emulated seconds per real second")
    emu.add_argument("--faults", default="", help="fault spec, e.g. checksum_every=50,drop_every=70,reboot_at=400")
    emu.add_argument("--duration", type=float, default=None, help="stop after this many real seconds")
    emu.set_defaults(func=_emulate)

    bench = sub.add_parser("bench", help="decode throughput of 1081-step ME scans, ours vs hokuyolx",
                           description="Decode the same ME scan messages with this codec and with hokuyolx's "
                           "decoder; print scans/s for both and the ratio (target: >= 20x).")
    bench.add_argument("-n", "--scans", type=int, default=200, help="distinct messages (default 200)")
    bench.add_argument("--seconds", type=float, default=2.0, help="minimum timing per decoder (default 2)")
    bench.add_argument("--no-hokuyolx", action="store_true", help="time only this codec")
    bench.set_defaults(func=_bench)


def _stream_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--multi-echo", action="store_true", help="NE (multi-echo) instead of ME")
    p.add_argument("--start", type=int, default=None, help="first step (default: PP AMIN)")
    p.add_argument("--end", type=int, default=None, help="last step (default: PP AMAX)")
    p.add_argument("--cluster", type=int, default=1, help="steps per beam (default 1)")
    p.add_argument("--skip", type=int, default=0, help="scans skipped between two sent, 0-9 (default 0)")


def _settings(args):
    from drivers.hokuyo.client import HokuyoSettings

    return HokuyoSettings(multi_echo=args.multi_echo, start_step=args.start, end_step=args.end,
                          cluster=args.cluster, skip=args.skip)


def _fail(exc: BaseException) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return 1


def _run(main) -> int:
    """Run a coroutine; driver errors and bad arguments become a one-line message and exit code 1."""
    from drivers.errors import DriverError

    try:
        asyncio.run(main)
    except (DriverError, ValueError, OSError) as exc:
        return _fail(exc)
    return 0


def _probe(args) -> int:
    from drivers.hokuyo.client import HokuyoClient, HokuyoSettings

    async def run() -> None:
        client = await HokuyoClient.connect(args.url, HokuyoSettings(stream=False))
        try:
            for title, fields in (("VV", client.version), ("PP", client.pp),
                                  ("II", client.status)):
                print(f"{title}:")
                for k, v in (fields or {}).items():
                    print(f"  {k}: {v}")
            g = client.geometry
            print(f"geometry: {g.n_beams} beams, {g.angle_min:.4f} rad + k * {g.angle_increment:.6f} rad, "
                  f"{g.range_min:.3f}-{g.range_max:.1f} m, {g.scan_time * 1000:.1f} ms per scan")
        finally:
            await client.close()

    return _run(run())


def _stream(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from drivers.hokuyo.client import HokuyoClient

    async def run() -> None:
        async with HokuyoClient.connect(args.url, _settings(args)) as client:
            t0, n = time.monotonic(), 0
            with tqdm(total=args.scans, unit="scan", file=sys.stderr) as bar:
                async for scan in client.scans():
                    n += 1
                    bar.update()
                    if n >= args.scans:
                        break
            dt = time.monotonic() - t0
            print(f"{n} scans in {dt:.2f} s: {n / dt:.1f} scans/s")
            if n:
                print(f"last scan: {scan.ranges.size} beams, {int(np.isfinite(scan.ranges).sum())} with a "
                      f"range, sensor stamp {scan.sensor_stamp:.3f} s")
                g = scan.geometry  # the beams within 0.5 deg of the sensor's front (0 rad)
                k = np.abs(g.angle_min + g.angle_increment * np.arange(scan.ranges.size)) <= np.radians(0.5)
                ahead = scan.ranges[k][np.isfinite(scan.ranges[k])]
                print(f"straight ahead: {np.median(ahead):.3f} m" if ahead.size else "straight ahead: no return")
            print("counters: " + ", ".join(f"{k}={v}" for k, v in vars(client.stats).items()))

    return _run(run())


def _record(args) -> int:
    from drivers.hokuyo.client import record

    async def run() -> None:
        stats = await record(args.url, args.file, _settings(args), scans=args.scans, note=args.note)
        print(f"recorded {stats.received} scans to {args.file} (corrupted={stats.corrupted}, "
              f"reconnects={stats.reconnects})")

    return _run(run())


def _emulate(args) -> int:
    from drivers.hokuyo.emulator import Faults, HokuyoEmulator, room_scan_source, sim_scan_source

    try:
        faults = Faults.parse(args.faults)
        if args.world:
            from glassmap.sim.world import load_world

            world = load_world(args.world)
            pose = world.start_pose
            source = sim_scan_source(world, lambda t: pose)
        else:
            source = room_scan_source()
    except ValueError as exc:
        return _fail(exc)

    async def run() -> None:
        emu = HokuyoEmulator(source, time_scale=args.time_scale, faults=faults)
        url = await (emu.serve_pty() if args.pty else emu.serve_tcp(port=args.port))
        print(f"emulated UTM-30LX-EW at {url} (Ctrl-C to stop)", flush=True)
        try:
            if args.duration is None:
                await asyncio.Event().wait()
            await asyncio.sleep(args.duration)
        finally:
            await emu.close()
            print("emulator: " + ", ".join(f"{k}={v}" for k, v in vars(emu.stats).items() if k != "good_stamps"))

    return _run(run())


def _bench(args) -> int:
    from drivers.hokuyo.bench import hokuyolx_available, run_bench

    if args.scans < 1 or args.seconds <= 0:
        return _fail(ValueError("--scans must be >= 1 and --seconds > 0"))
    with_ref = not args.no_hokuyolx
    if with_ref and not hokuyolx_available():
        print("note: hokuyolx is not installed: comparison skipped (pip install hokuyolx, or "
              "pip install 'glassmap[test]')")
        with_ref = False
    r = run_bench(args.scans, args.seconds, with_hokuyolx=with_ref)
    print(f"ours:     {r.ours_scans_per_s:10.1f} scans/s  (1081-step ME, checksums verified)")
    if r.hokuyolx_scans_per_s is not None:
        print(f"hokuyolx: {r.hokuyolx_scans_per_s:10.1f} scans/s")
        print(f"speed-up: {r.speedup:10.1f}x (target >= 20x)")
    return 0
