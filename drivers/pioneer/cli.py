"""``glassmap pioneer ...``: probe, drive (scripted or keyboard), emulate and bench the Pioneer 3-DX driver.

Safety: every command that drives runs inside the client's context manager; Ctrl-C (SIGINT) and SIGTERM
cancel the main task, so the client stops the robot (VEL 0, RVEL 0, ENABLE 0, CLOSE) before the process
exits, and keyboard teleoperation restores the terminal on every exit path.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import signal
import sys
import time
from collections.abc import Awaitable, Callable

from drivers.pioneer.motion_guard import ReconnectGuard
from glassmap.cli_args import add_seed, add_seeds

URL_HELP = ("robot URL: serial:///dev/ttyUSB0 (9600 baud at power-up; ?baud=N to override) or "
            "tcp://HOST:8101 (a simulator)")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("pioneer", help="Pioneer 3-DX base: probe, drive, emulate, eval (odometry covariance), bench",
                              description="Talk to a Pioneer 3-DX base (ARCOS/P2OS protocol) or emulate one.")
    sub = p.add_subparsers(dest="pioneer_command", required=True, metavar="ACTION")

    pr = sub.add_parser("probe", help="handshake, print name/class/subclass and a few SIPs, close",
                        description="Connect (motors stay disabled), print the robot's identity, the "
                        "conversion factors, optionally its CONFIG packet, and decoded SIPs; then close.")
    pr.add_argument("url", help=URL_HELP)
    pr.add_argument("--sips", type=int, default=5, help="number of SIPs to print (default 5)")
    pr.add_argument("--config", action="store_true", help="also request and print the CONFIG packet")
    _common(pr)
    pr.set_defaults(func=_probe)

    dr = sub.add_parser("drive", help="drive a short scripted motion, or from the keyboard",
                        description="Enable the motors and drive: a square (default, 0.5 m sides), a "
                        "straight line, or keyboard teleoperation. Ctrl-C stops the robot at once.")
    dr.add_argument("url", help=URL_HELP)
    how = dr.add_mutually_exclusive_group()
    how.add_argument("--square", type=float, metavar="SIDE", help="drive a square with SIDE-metre sides, "
                     "turning left (default: 0.5)")
    how.add_argument("--line", type=float, metavar="DIST", help="drive DIST metres straight (negative: back)")
    how.add_argument("--teleop", action="store_true", help="keyboard: w/s or up/down speed, a/d or "
                     "left/right turn, space stop, x emergency stop, q quit")
    dr.add_argument("--speed", type=float, default=0.2, help="forward speed for scripts, m/s (default 0.2)")
    dr.add_argument("--turn-rate", type=float, default=30.0, help="turn rate for scripts, deg/s (default 30)")
    dr.add_argument("--continue-after-reconnect", action="store_true", help="after a lost and re-opened "
                    "link, carry on with the scripted motion (default: stop and report)")
    dr.add_argument("--max-speed", type=float, default=0.5, help="client speed limit, m/s (default 0.5)")
    dr.add_argument("--max-turn-rate", type=float, default=60.0, help="client turn-rate limit, deg/s "
                    "(default 60)")
    _common(dr)
    dr.set_defaults(func=_drive)

    em = sub.add_parser("emulate", help="run an emulated P3-DX controller on a pty or loopback TCP",
                        description="Serve an emulated Pioneer 3-DX (simulator kinematics) until Ctrl-C. "
                        "Prints the URL to give to probe/drive or the runtime.")
    em.add_argument("--tcp", type=int, metavar="PORT", help="serve on tcp://127.0.0.1:PORT (0 = any free "
                    "port) instead of a pseudo-terminal")
    em.add_argument("--time-scale", type=float, default=1.0, help="run faster than real time (default 1)")
    em.add_argument("--subclass", choices=("p3dx", "p3dx-sh"), default="p3dx-sh", help="robot subclass")
    em.add_argument("--simulator-deviations", action="store_true", help="behave like the known simulator "
                    "(16-bit positions, 0x32 always, motors enabled, watchdog only logs, all sonar)")
    em.add_argument("--corrupt-rate", type=float, default=0.0, help="probability per packet of a corrupted "
                    "byte")
    em.add_argument("--drop-rate", type=float, default=0.0, help="probability per packet of dropped bytes")
    em.add_argument("--garbage-rate", type=float, default=0.0, help="probability per packet of garbage before it")
    em.add_argument("--still-open", action="store_true", help="start as if left open by an earlier session")
    add_seed(em, what="seed of the odometry noise and the faults")
    em.set_defaults(func=_emulate)

    ev = sub.add_parser("eval", help="odometry covariance consistency (NEES) against the emulator's robot",
                        description="Drive straight (2 m) and turn in place (360 deg) with the emulator's "
                        "simulated P3-DX over many seeds, feed its SIPs through the driver's odometry tracker and "
                        "compare the final error with the reported covariance: mean NEES (3 dof, ideal 3) and the "
                        "share of runs inside the 95 % bound. 'emulator': the emulator's robot (fixed wheel-scale "
                        "and track-width errors); 'drawn': a robot per seed with errors drawn from the model.")
    add_seeds(ev, "0-199")
    ev.add_argument("--robot", choices=("emulator", "drawn", "both"), default="both",
                    help="which robots (default: %(default)s)")
    ev.set_defaults(func=_eval)

    be = sub.add_parser("bench", help="codec throughput: parse, decode and integrate SIPs",
                        description="Measure the sans-IO codec: packets/s through the parser (clean and with "
                        "garbage), SIP decoding and odometry integration.")
    be.add_argument("--packets", type=int, default=20000, help="number of SIPs (default 20000)")
    be.set_defaults(func=_bench)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--time-scale", type=float, default=1.0, help="the robot runs this much faster than real "
                   "time (an emulator started with --time-scale); scales the client's timers (default 1)")
    p.add_argument("--high-baud", type=int, choices=(19200, 38400, 57600, 115200), help="serial only: switch "
                   "to this speed after connecting")
    p.add_argument("--model", choices=("p3dx", "p3dx-sh"), help="force the conversion factors instead of "
                   "the reported subclass")


def _settings(args: argparse.Namespace, **extra: object):
    from drivers.pioneer.client import PioneerSettings

    return PioneerSettings(time_scale=args.time_scale, high_baud=args.high_baud, model=args.model, **extra)


def run_until_signal(main: Callable[[], Awaitable[int]]) -> int:
    """Run ``main()`` in a new event loop; SIGINT and SIGTERM cancel it (so its cleanup runs). Exit code."""
    stopped: list[int] = []

    async def runner() -> int:
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        assert task is not None
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda s=sig: (stopped.append(s), task.cancel()))
        try:
            return await main()
        finally:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)

    try:
        return asyncio.run(runner())
    except asyncio.CancelledError:
        if not stopped:
            raise
        print(f"stopped by {signal.Signals(stopped[0]).name}: robot stopped, connection closed", file=sys.stderr)
        return 128 + stopped[0]


def _fail(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 1


# -- probe ---------------------------------------------------------------------------------------------
def _probe(args: argparse.Namespace) -> int:
    from drivers.errors import DriverError
    from drivers.pioneer.client import PioneerClient
    from drivers.pioneer.errors import HandshakeError

    if args.sips < 0:
        return _fail("--sips must be >= 0")

    async def main() -> int:
        async with PioneerClient.connect(args.url, _settings(args, read_config=args.config)) as base:
            info, m = base.info, base.model
            if info is None or m is None:
                raise HandshakeError(f"{args.url}: connected without a SYNC2 reply")
            print(f"name: {info.name}\nclass: {info.robot_class}\nsubclass: {info.subclass}")
            print(f"conversion: {m.dist_conv} mm/unit, {m.angle_conv} rad/unit, DiffConv {m.diff_conv}")
            if args.config:
                print(f"config: {base.config}")
            n = 0
            async with contextlib.aclosing(base.odometry()) as poses:
                async for odom in poses:
                    if n >= args.sips:
                        break
                    sip, st = base.last_sip, base.state
                    if sip is None or st is None:  # odometry comes from a SIP: both are set by then
                        continue
                    print(f"SIP 0x{0x33 if sip.moving else 0x32:02x} x={odom.x:+.3f} m y={odom.y:+.3f} m "
                          f"yaw={math.degrees(odom.yaw):+7.2f} deg v={odom.v:+.3f} m/s "
                          f"omega={math.degrees(odom.omega):+6.1f} deg/s battery={st.battery_volts:.1f} V "
                          f"motors={'on' if st.motors_enabled else 'off'} stall={int(st.stalled)} "
                          f"bumpers={st.front_bumpers:#04x}/{st.rear_bumpers:#04x} sonar={len(sip.sonar)} new")
                    n += 1
            print(f"stats: {base.stats}")
        return 0

    try:
        return run_until_signal(main)
    except (DriverError, ValueError) as exc:
        return _fail(str(exc))


# -- drive ---------------------------------------------------------------------------------------------
def _drive(args: argparse.Namespace) -> int:
    from drivers.errors import DriverError
    from drivers.pioneer.client import PioneerClient
    from drivers.pioneer.motion_guard import MotionInterrupted

    if args.speed <= 0 or args.turn_rate <= 0:
        return _fail("--speed and --turn-rate must be > 0")
    if args.teleop and not sys.stdin.isatty():
        return _fail("--teleop needs an interactive terminal on stdin")
    settings = _settings(args, max_v=args.max_speed, max_omega=math.radians(args.max_turn_rate))

    async def main() -> int:
        async with PioneerClient.connect(args.url, settings, enable_motors=True) as base:
            resume = args.continue_after_reconnect
            try:
                if args.teleop:
                    await teleoperate(base)
                elif args.line is not None:
                    await drive_distance(base, args.line, args.speed, resume=resume)
                else:
                    await drive_square(base, args.square if args.square is not None else 0.5, args.speed,
                                       math.radians(args.turn_rate), resume=resume)
            except MotionInterrupted:
                await base.stop()
                raise
            await base.stop()
            odom = base.latest
            if odom is None:  # connect waits for the first SIP, so this does not happen
                return _fail("no odometry from the robot")
            print(f"final odometry: x={odom.x:+.3f} m y={odom.y:+.3f} m yaw={math.degrees(odom.yaw):+.2f} deg "
                  f"(sigma_x={math.sqrt(odom.covariance[0, 0]):.3f} m, "
                  f"sigma_yaw={math.degrees(math.sqrt(odom.covariance[2, 2])):.2f} deg)")
        return 0

    try:
        return run_until_signal(main)
    except (DriverError, ValueError, TimeoutError) as exc:
        return _fail(str(exc))


async def drive_distance(base, distance: float, speed: float, *, decel: float = 0.25,
                         timeout: float | None = None, resume: bool = False) -> None:
    """Drive ``distance`` m straight (negative: backwards) at up to ``speed`` m/s, holding the heading.

    Slows down so that a deceleration of ``decel`` m/s^2 (below the P3-DX default 0.3) stops it on the spot.
    A reconnect on the way raises MotionInterrupted unless ``resume``.
    """
    guard = ReconnectGuard(base, resume, f"drive of {distance:+.2f} m")
    start = base.latest
    goal = abs(distance)
    sign = 1.0 if distance >= 0 else -1.0
    limit = timeout if timeout is not None else (3.0 * goal / speed + 5.0) / base.settings.time_scale
    t_end = time.monotonic() + limit
    async with contextlib.aclosing(base.odometry()) as poses:
        async for odom in poses:
            guard.check()
            done = math.hypot(odom.x - start.x, odom.y - start.y)
            remaining = goal - done
            if remaining <= 0.005:
                break
            if time.monotonic() > t_end:
                raise TimeoutError(f"drove {done:.2f} of {goal:.2f} m in {limit:.0f} s: is the robot blocked, "
                                   "its motors enabled (MOTORS button), its e-stop released?")
            err = math.atan2(math.sin(start.yaw - odom.yaw), math.cos(start.yaw - odom.yaw))
            v = sign * min(speed, max(0.03, math.sqrt(2.0 * decel * remaining)))
            await base.set_velocity(v, 1.5 * err)
    await base.stop()


async def turn_by(base, angle: float, rate: float, *, decel: float = math.radians(70.0),
                  timeout: float | None = None, resume: bool = False) -> None:
    """Turn in place by ``angle`` rad (CCW +) at up to ``rate`` rad/s, slowing down at ``decel`` rad/s^2.

    A reconnect on the way raises MotionInterrupted unless ``resume``."""
    guard = ReconnectGuard(base, resume, f"turn of {math.degrees(angle):+.0f} deg")
    start = base.latest
    goal_yaw = start.yaw + angle
    limit = timeout if timeout is not None else (3.0 * abs(angle) / rate + 5.0) / base.settings.time_scale
    t_end = time.monotonic() + limit
    async with contextlib.aclosing(base.odometry()) as poses:
        async for odom in poses:
            guard.check()
            err = math.atan2(math.sin(goal_yaw - odom.yaw), math.cos(goal_yaw - odom.yaw))
            if abs(err) < math.radians(1.0):
                break
            if time.monotonic() > t_end:
                raise TimeoutError(f"turn not finished in {limit:.0f} s ({math.degrees(err):.1f} deg left)")
            w = math.copysign(min(rate, max(math.radians(3.0), math.sqrt(2.0 * decel * abs(err)))), err)
            await base.set_velocity(0.0, w)
    await base.stop()


async def drive_square(base, side: float, speed: float, rate: float, *, resume: bool = False) -> None:
    """Drive a square of ``side`` m turning left at each corner; ends near the start pose."""
    guard = ReconnectGuard(base, resume, "square")
    for _ in range(4):
        await drive_distance(base, side, speed, resume=resume)
        guard.check()
        await turn_by(base, math.pi / 2, rate, resume=resume)
        guard.check()


KEY_HELP = "w/s or up/down: speed  a/d or left/right: turn  space: stop  x: e-stop  q: quit"


async def teleoperate(base, *, step_v: float = 0.05, step_w: float = math.radians(10.0)) -> None:
    """Keyboard teleoperation on stdin (cbreak mode, restored on every exit). Sends the setpoint at 10 Hz."""
    import termios
    import tty

    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    loop = asyncio.get_running_loop()
    keys: asyncio.Queue[bytes] = asyncio.Queue()
    v = w = 0.0
    reconnects = base.stats.reconnects
    try:
        tty.setcbreak(fd)
        loop.add_reader(fd, lambda: keys.put_nowait(os.read(fd, 32)))
        print(KEY_HELP, file=sys.stderr)
        while True:
            with contextlib.suppress(asyncio.TimeoutError):
                data = await asyncio.wait_for(keys.get(), 0.1)
                for key in _split_keys(data):
                    if key in ("q", "\x1b"):
                        return
                    if key in ("w", "up"):
                        v += step_v
                    elif key in ("s", "down"):
                        v -= step_v
                    elif key in ("a", "left"):
                        w += step_w
                    elif key in ("d", "right"):
                        w -= step_w
                    elif key == " ":
                        v = w = 0.0
                    elif key == "x":
                        v = w = 0.0
                        await base.estop()
            if base.stats.reconnects != reconnects:  # back at rest after a lost link: stay there
                reconnects = base.stats.reconnects
                v = w = 0.0
                sys.stderr.write("\nlink lost and re-opened: stopped; drive on with the keys\n")
            s = base.settings
            v = max(-s.max_v, min(s.max_v, v))
            w = max(-s.max_omega, min(s.max_omega, w))
            await base.set_velocity(v, w)
            o = base.latest
            sys.stderr.write(f"\rv={v:+.2f} m/s w={math.degrees(w):+5.0f} deg/s  x={o.x:+7.2f} y={o.y:+7.2f} "
                             f"yaw={math.degrees(o.yaw):+7.1f}  battery={base.state.battery_volts:4.1f} V   ")
            sys.stderr.flush()
    finally:
        loop.remove_reader(fd)
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)
        sys.stderr.write("\n")


def _split_keys(data: bytes) -> list[str]:
    arrows = {b"\x1b[A": "up", b"\x1b[B": "down", b"\x1b[C": "right", b"\x1b[D": "left"}
    out, i = [], 0
    while i < len(data):
        seq = data[i:i + 3]
        if seq in arrows:
            out.append(arrows[seq])
            i += 3
            continue
        out.append(chr(data[i]).lower())
        i += 1
    return out


# -- emulate -------------------------------------------------------------------------------------------
def _emulate(args: argparse.Namespace) -> int:
    from drivers.pioneer.emulator import EmulatorFaults, PioneerEmulator

    try:
        faults = EmulatorFaults(corrupt_rate=args.corrupt_rate, drop_rate=args.drop_rate,
                                garbage_rate=args.garbage_rate, still_open=args.still_open, seed=args.seed)
        emu = PioneerEmulator(time_scale=args.time_scale, real_robot=not args.simulator_deviations,
                              faults=faults, subclass=args.subclass, seed=args.seed)
    except ValueError as exc:
        return _fail(str(exc))

    async def main() -> int:
        try:
            url = await (emu.serve_tcp(args.tcp) if args.tcp is not None else emu.serve_pty())
        except OSError as exc:  # e.g. the port is in use
            await emu.close()
            where = f"tcp port {args.tcp}" if args.tcp is not None else "a pseudo-terminal"
            return _fail(f"cannot serve on {where}: {exc.strerror or exc}")
        print(url, flush=True)
        print("emulating a Pioneer 3-DX; Ctrl-C to stop", file=sys.stderr)
        try:
            while True:
                await asyncio.sleep(3600)
        finally:
            await emu.close()

    rc = run_until_signal(main)
    return 0 if rc in (128 + signal.SIGINT, 128 + signal.SIGTERM) else rc


# -- bench ---------------------------------------------------------------------------------------------
def _eval(args) -> int:
    from drivers.pioneer.odometry_eval import MOTIONS, evaluate, format_result

    kinds = ("emulator", "drawn") if args.robot == "both" else (args.robot,)
    for motion in MOTIONS:
        for kind in kinds:
            print(format_result(evaluate(motion, kind, args.seeds)), flush=True)
    return 0


def _bench(args: argparse.Namespace) -> int:
    import random

    from drivers.pioneer.odometry import MODELS, OdometryTracker
    from drivers.pioneer.packets import PacketParser
    from drivers.pioneer.sip import StandardSIP, decode_sip, encode_sip

    n = args.packets
    if n <= 0:
        return _fail("--packets must be > 0")
    rng = random.Random(0)
    sips = [encode_sip(StandardSIP(True, (7 * k) & 0x7FFF, (3 * k) & 0x7FFF, (k % 4096) - 2048, 300, 310, 126,
                                   sonar=tuple((j, 1500 + j) for j in range(4)), battery_x10=126, rotvel=10))
            for k in range(n)]
    clean = b"".join(sips)
    noisy = b"".join(bytes(rng.randrange(256) for _ in range(rng.randint(0, 8))) + s for s in sips)

    def parse(stream: bytes) -> tuple[float, int]:
        p = PacketParser()
        t0 = time.perf_counter()
        got = 0
        for i in range(0, len(stream), 4096):
            got += len(p.feed(stream[i:i + 4096], 0.0))
        return time.perf_counter() - t0, got

    dt_clean, got_clean = parse(clean)
    dt_noisy, got_noisy = parse(noisy)
    payloads = [s[4:-2] for s in sips]
    t0 = time.perf_counter()
    decoded = [decode_sip(0x33, p) for p in payloads]
    dt_dec = time.perf_counter() - t0
    tracker = OdometryTracker(MODELS["p3dx-sh"])
    t0 = time.perf_counter()
    for k, s in enumerate(decoded):
        tracker.update(s, k * 0.1)
    dt_odo = time.perf_counter() - t0
    print(f"SIPs: {n} of {len(sips[0])} bytes")
    print(f"parse clean : {got_clean / dt_clean:10.0f} packets/s  {len(clean) / dt_clean / 1e6:6.2f} MB/s")
    print(f"parse noisy : {got_noisy / dt_noisy:10.0f} packets/s  {len(noisy) / dt_noisy / 1e6:6.2f} MB/s "
          f"(random garbage between packets; {got_noisy}/{n} recovered)")
    print(f"decode SIP  : {n / dt_dec:10.0f} SIPs/s")
    print(f"odometry    : {n / dt_odo:10.0f} SIPs/s (unwrap + covariance)")
    print("(the robot sends 10 SIPs/s)")
    return 0

