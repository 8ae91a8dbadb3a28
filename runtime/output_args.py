"""Command-line flags of the runtime's outputs (live view, recording splits) and their parsing; light
(no heavy imports), so that ``glassmap --help`` stays fast."""

from __future__ import annotations

import re
from pathlib import Path


class LiveViewError(OSError):
    """The live view cannot start (bad address, port in use, foxglove-sdk missing)."""


def parse_address(text: str) -> tuple[str, int]:
    """``PORT`` (loopback) or ``HOST:PORT`` -> (host, port). Port 0 picks a free port."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep:
        host = "127.0.0.1"
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise LiveViewError(f"--live {text!r}: expected PORT or HOST:PORT (e.g. 8765 or 0.0.0.0:8765)")
    return host, int(port)


def add_live_arg(parser) -> None:
    """The ``--live [HOST:]PORT`` flag (= output.live) of run, demo and replay."""
    parser.add_argument("--live", metavar="[HOST:]PORT", default=None,
                        help="serve the live view to Foxglove (WebSocket) on this port, loopback unless a host is "
                        "given, e.g. 8765 or 0.0.0.0:8765 (= output.live)")


_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)i?b?\s*$", re.IGNORECASE)


def parse_size(text: str | int) -> int:
    """A size in bytes from ``123``, ``500k``, ``500M``, ``2G`` (powers of 1024)."""
    m = _SIZE.match(str(text))
    if not m:
        raise ValueError(f"size {text!r}: expected bytes or a number with k, M, G (e.g. 500M)")
    return int(float(m.group(1)) * 1024 ** " KMGT".index(m.group(2).upper() or " "))


def add_split_args(parser) -> None:
    """``--record-split-size SIZE`` and ``--record-split-duration S`` (= output.record_split_*)."""
    parser.add_argument("--record-split-size", metavar="SIZE", default=None,
                        help="split the recording into files of about SIZE (e.g. 500M, 2G): <stem>_0000.mcap, "
                        "<stem>_0001.mcap, ... (= output.record_split_size)")
    parser.add_argument("--record-split-duration", metavar="S", type=float, default=None,
                        help="split the recording every S seconds (= output.record_split_duration)")


def apply_split_args(args, output) -> None:
    """Copy the split flags, if given, into an :class:`runtime.config.OutputConfig`."""
    if getattr(args, "record_split_size", None) is not None:
        output.record_split_size = parse_size(args.record_split_size)
    if getattr(args, "record_split_duration", None) is not None:
        output.record_split_duration = args.record_split_duration


def describe_files(files: list[str]) -> str:
    """The recording's file(s) for a summary line: one path, or the first .. last and how many."""
    if len(files) <= 1:
        return files[0] if files else ""
    return f"{files[0]} .. {Path(files[-1]).name} ({len(files)} files)"
