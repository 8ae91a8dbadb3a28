"""Keyboard teleoperation for ``glassmap run --teleop`` (the only way ``run`` moves the robot).

Keys: w/s faster/slower forward (steps of 0.1 m/s), a/d turn left/right (steps of 15 deg/s), space stop,
q quit the run. The terminal is put in cbreak mode while driving and always restored on exit. Commands are
re-sent every 0.2 s (the base stops by itself when they stop coming).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import sys
import termios
import tty

from drivers.errors import DriverError

V_STEP = 0.1
W_STEP = math.radians(15)
HELP = "teleop: w/s speed, a/d turn, space stop, q quit"


def key_to_command(key: str, v: float, w: float, max_v: float, max_w: float) -> tuple[float, float, bool]:
    """New (v, omega, quit) after one key press; unknown keys change nothing."""
    if key == "w":
        v = min(max_v, v + V_STEP)
    elif key == "s":
        v = max(-max_v, v - V_STEP)
    elif key == "a":
        w = min(max_w, w + W_STEP)
    elif key == "d":
        w = max(-max_w, w - W_STEP)
    elif key == " ":
        v, w = 0.0, 0.0
    elif key in ("q", "\x03"):
        return 0.0, 0.0, True
    return round(v, 3), w, False


@contextlib.contextmanager
def cbreak_terminal(fd: int):
    """Single key presses without Enter; the previous terminal settings are restored on exit."""
    old = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


def keyboard_driver(max_v: float, max_w: float):
    """A runtime driver (see :class:`runtime.app.Runtime`) reading keys from the terminal."""

    async def drive(rt) -> None:
        if not sys.stdin.isatty():
            raise RuntimeError("--teleop needs an interactive terminal (stdin is not a tty)")
        loop = asyncio.get_running_loop()
        keys: asyncio.Queue[str] = asyncio.Queue()
        fd = sys.stdin.fileno()
        print(HELP, file=sys.stderr)
        with cbreak_terminal(fd):
            loop.add_reader(fd, lambda: keys.put_nowait(os.read(fd, 1).decode(errors="ignore")))
            try:
                v = w = 0.0
                while True:
                    try:
                        key = await asyncio.wait_for(keys.get(), 0.2)
                        v, w, quit_ = key_to_command(key, v, w, max_v, max_w)
                        if quit_:
                            with contextlib.suppress(DriverError):
                                await rt.command_velocity(0.0, 0.0)
                            return
                    except asyncio.TimeoutError:
                        pass
                    with contextlib.suppress(DriverError):
                        await rt.command_velocity(v, w)
            finally:
                loop.remove_reader(fd)

    return drive
