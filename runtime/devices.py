"""Emulated hardware in its own process: the simulated robot inside an emulated Pioneer (pseudo-terminal)
and an emulated Hokuyo (loopback TCP) ranging the simulated world from the robot's true laser pose.

Running the devices in a separate process keeps them off the runtime's interpreter (as real hardware is):
the runtime's event loop and processing thread do not share a GIL with the simulator. Inside it, the
Pioneer's controller runs its own event loop in its own thread, as a controller board runs beside the
laser: its SIP cycle does not wait for the laser's ray casting (compiled, it releases the GIL), so a
loaded machine makes the emulated laser late, not the controller's SIPs.

Protocol (line-oriented JSON on stdin/stdout):
- on start the process prints ``{"laser": URL, "base": URL}``;
- commands on stdin: ``laser-disconnect`` (cable pull; the link comes back), ``base-link-loss SECONDS``,
  ``pose`` (prints ``{"true_pose": [x, y, yaw]}``), ``quit``; end of input also quits;
- on exit it prints ``{"true_pose": [x, y, yaw], "odom_pose": [...], "laser_scans": N}`` and returns 0.

Run by hand: ``python -m runtime.devices --world office --speed 2``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import sys
import threading
from dataclasses import dataclass

import numpy as np

from runtime.tuning import ONE_THREAD_ENV


class SeenCells:
    """Blueprint cells hit by the simulated laser's returned beams (true end points from the true pose), on
    ``Blueprint.from_world(world, resolution)``'s grid: the ground truth of which walls were seen."""

    def __init__(self, world, resolution: float = 0.05) -> None:
        from glassmap.sim.blueprint import Blueprint

        bp = Blueprint.from_world(world, resolution=resolution)
        self.origin, self.resolution = bp.origin, bp.resolution
        self.mask = np.zeros(bp.labels.shape, dtype=bool)

    def add(self, laser_pose: np.ndarray, sim) -> None:
        ret = np.isfinite(sim.ranges) & np.isfinite(sim.true_range)
        ang = laser_pose[2] + sim.geometry.angles[ret]
        ex = np.round(laser_pose[0] + sim.true_range[ret] * np.cos(ang), 6)
        ey = np.round(laser_pose[1] + sim.true_range[ret] * np.sin(ang), 6)
        cx = np.floor((ex - self.origin[0]) / self.resolution).astype(np.int64)
        cy = np.floor((ey - self.origin[1]) / self.resolution).astype(np.int64)
        h, w = self.mask.shape
        ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        self.mask[cy[ok], cx[ok]] = True


class TruthLog:
    """The robot's true pose (x, y, yaw; world = map frame) when each simulated scan was taken, keyed by that
    scan's 24-bit sensor stamp (ms): the ground truth to score the estimate of the same scan against.
    ``clock``: the emulated laser's ``clock_ms(t)``, set once the emulator exists."""

    def __init__(self) -> None:
        self.clock = None
        self.rows: list[tuple[float, float, float, float]] = []

    def add(self, t: float, pose) -> None:
        if self.clock is not None:
            self.rows.append((float(self.clock(t)), float(pose[0]), float(pose[1]), float(pose[2])))

    def save(self, path: str) -> None:
        """(n, 4) array: sensor stamp (ms, 24-bit), x, y, yaw."""
        np.save(path, np.asarray(self.rows, np.float64).reshape(-1, 4))


def _pose_at(robot, t: float | None, cycle: float | None, speed: float) -> np.ndarray:
    """The robot's true pose (x, y, yaw; map frame) at monotonic time ``t`` (s): its state at the controller's
    last cycle (monotonic ``cycle``) moved on at its velocity, so a scan shows the pose of its stamp however
    late the emulator's loop runs (the controller steps the robot once per SIP cycle)."""
    pose = robot.true_pose
    if t is None or cycle is None:
        return pose
    dt = (t - cycle) * speed  # robot seconds
    v, w = robot.velocity
    return np.array([pose[0] + v * dt * np.cos(pose[2] + 0.5 * w * dt),
                     pose[1] + v * dt * np.sin(pose[2] + 0.5 * w * dt), pose[2] + w * dt])


async def serve(world_name: str, speed: float, seed: int, seen_path: str | None = None, out=sys.stdout,
                truth_path: str | None = None) -> int:
    from drivers.hokuyo.emulator import HokuyoEmulator, sim_scan_source
    from drivers.pioneer.emulator import PioneerEmulator
    from glassmap.sim.robot import DiffDriveRobot, RobotParams, compose
    from glassmap.sim.world import load_world

    world = load_world(world_name)
    robot = DiffDriveRobot(params=RobotParams(), pose0=tuple(world.start_pose), rng=np.random.default_rng(seed))
    pioneer = PioneerEmulator(robot, time_scale=speed, seed=seed)
    seen = SeenCells(world)
    truth = TruthLog()

    def laser_pose(t: float):  # called once per scan, at the pose the scan is ranged from
        with pioneer.lock:  # the robot and its cycle time as of one controller cycle
            pose = _pose_at(robot, hokuyo.loop_time(t), pioneer.cycle_monotonic, speed)
        truth.add(t, pose)
        return compose(pose, np.asarray(robot.params.laser_offset, np.float64))

    from glassmap.sim.cast_jit import warm_up
    from runtime.tuning import release_compiler_pages

    warm_up()  # the ray casting's compiled kernel, before the host connects (its laser watchdog is 0.5 s)
    # LLVM's pages out before the runtime loads its kernels: pages both processes map stay in both (runtime.tuning)
    release_compiler_pages()
    source = sim_scan_source(world, laser_pose, seed + 1, on_scan=seen.add)
    hokuyo = HokuyoEmulator(source, time_scale=speed)
    truth.clock = hokuyo.clock_ms
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def say(obj) -> None:
        out.write(json.dumps(obj) + "\n")
        out.flush()

    controller = asyncio.new_event_loop()
    controller_thread = threading.Thread(target=controller.run_forever, name="pioneer-controller", daemon=True)
    controller_thread.start()

    async def on_controller(coro):
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, controller))

    try:
        base_url = await on_controller(pioneer.serve_pty())
        laser_url = await hokuyo.serve_tcp(port=0)
        say({"laser": laser_url, "base": base_url})
        reader = asyncio.StreamReader()
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        stop_task = asyncio.create_task(stop.wait())
        while True:
            line_task = asyncio.create_task(reader.readline())
            done, _ = await asyncio.wait({line_task, stop_task}, return_when=asyncio.FIRST_COMPLETED)
            if stop_task in done:
                line_task.cancel()
                break
            raw = line_task.result()
            line = raw.decode().strip()
            if not raw or line == "quit":  # end of input, or asked to
                break
            if not line:
                continue
            cmd, *args = line.split()
            if cmd == "laser-disconnect":
                await hokuyo.disconnect()
            elif cmd == "base-link-loss":
                controller.call_soon_threadsafe(pioneer.link_loss, float(args[0]) if args else None)
            elif cmd == "pose":
                with pioneer.lock:
                    say({"true_pose": robot.true_pose.tolist()})
    finally:
        state = {"laser_state": hokuyo.state, "base_open": pioneer.is_open}
        await hokuyo.close()
        await on_controller(pioneer.close())
        controller.call_soon_threadsafe(controller.stop)
        controller_thread.join(timeout=5.0)
        if not controller_thread.is_alive():
            controller.close()
    if seen_path:
        np.save(seen_path, seen.mask)
    if truth_path:
        truth.save(truth_path)
    say({"true_pose": robot.true_pose.tolist(), "odom_pose": robot.odom_pose.tolist(),
         "velocity": list(robot.velocity), "commanded": list(pioneer.commanded_velocity),
         "motors_enabled": bool(pioneer.motors_enabled),
         "laser_state": state["laser_state"], "base_open_at_quit": bool(state["base_open"]),
         "laser_scans": int(hokuyo.stats.scans_good), "laser_disconnects": int(hokuyo.stats.disconnects)})
    return 0


@dataclass
class DeviceProcess:
    """The parent's handle on a running devices process."""

    proc: asyncio.subprocess.Process
    laser_url: str
    base_url: str

    @classmethod
    async def start(cls, world: str = "office", speed: float = 1.0, seed: int = 0,
                    seen_path: str | None = None, truth_path: str | None = None) -> DeviceProcess:
        """Start ``python -m runtime.devices``; ``seen_path`` / ``truth_path``: where it saves the seen-cells
        mask / the true pose of every scan (.npy, see :class:`TruthLog`) at exit."""
        if speed <= 0 or not math.isfinite(speed):
            raise ValueError(f"speed must be > 0, got {speed}")
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "runtime.devices", "--world", world, "--speed", str(speed), "--seed", str(seed),
            *(["--seen", seen_path] if seen_path else []), *(["--truth", truth_path] if truth_path else []),
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, env={**os.environ, **ONE_THREAD_ENV},
            start_new_session=True)  # Ctrl-C in the terminal reaches the runtime only, as with real devices
        try:
            line = await asyncio.wait_for(proc.stdout.readline(), 60.0)
            urls = json.loads(line)
        except (asyncio.TimeoutError, json.JSONDecodeError) as exc:
            proc.kill()
            await proc.wait()
            raise RuntimeError(f"the emulated devices did not start ({exc!r}); run "
                               f"`python -m runtime.devices --world {world}` to see why") from None
        return cls(proc, urls["laser"], urls["base"])

    async def command(self, line: str) -> None:
        self.proc.stdin.write((line + "\n").encode())
        await self.proc.stdin.drain()

    async def true_pose(self) -> np.ndarray:
        await self.command("pose")
        return np.asarray(json.loads(await self.proc.stdout.readline())["true_pose"])

    async def stop(self, timeout: float = 10.0) -> dict:
        """Quit the devices; returns their final report (true pose ...)."""
        try:
            self.proc.stdin.write(b"quit\n")
            await self.proc.stdin.drain()
            self.proc.stdin.close()
        except (ConnectionError, RuntimeError):
            pass
        report: dict = {}
        try:
            while True:
                line = await asyncio.wait_for(self.proc.stdout.readline(), timeout)
                if not line:
                    break
                obj = json.loads(line)
                if "laser_scans" in obj:
                    report = obj
        except (asyncio.TimeoutError, json.JSONDecodeError):
            self.proc.kill()
        await self.proc.wait()
        return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], prog="python -m runtime.devices")
    p.add_argument("--world", default="office", help="simulator world name or file (default: office)")
    p.add_argument("--speed", type=float, default=1.0, help="emulated time runs this many times faster")
    p.add_argument("--seed", type=int, default=0, help="random seed of the robot and laser noise")
    p.add_argument("--seen", default=None, help="save the blueprint cells the laser saw to this .npy at exit")
    p.add_argument("--truth", default=None, help="save the true pose of every scan (stamp ms, x, y, yaw) to this "
                   ".npy at exit")
    a = p.parse_args(argv)
    return asyncio.run(serve(a.world, a.speed, a.seed, a.seen, truth_path=a.truth))


if __name__ == "__main__":
    sys.exit(main())
