"""The ``glassmap`` command. Each subcommand lives in its own module with ``register(subparsers)``.

Subcommand modules must import heavy dependencies (torch, the simulator) inside their handlers, so that
``glassmap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

# Modules that add subcommands, in the order they appear in --help.
COMMAND_MODULES = [
    "glassmap.sim.cli",
    "glassmap.glass_cli",
    "glassmap.pose.cli",
    "drivers.pioneer.cli",
    "drivers.hokuyo.cli",
    "runtime.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glassmap",
        description="Online glass confidence maps from a 2D laser rangefinder: simulate, map, evaluate, "
        "drive the Hokuyo and the Pioneer, run on the robot, record and replay.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into head & co.: stop quietly, like other command-line tools
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
