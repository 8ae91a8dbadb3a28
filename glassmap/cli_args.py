"""Command-line flags shared by several ``glassmap`` commands, declared once.

Each ``add_*`` function adds one flag to an argparse parser with the same name, type and help everywhere;
only the default (and, where it matters, what the flag is used for) changes between commands.
"""

from __future__ import annotations

import argparse

BUILTIN_WORLDS = "office, glass-corridor, room, lobby"


def parse_seeds(text: str) -> list[int]:
    """Seeds from 'a,b,c' and ranges 'a-b' (inclusive), e.g. '0-2,7' -> [0, 1, 2, 7]."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a seed list: {text!r} (use e.g. 0,3 or 0-9)") from None
    if not out:
        raise argparse.ArgumentTypeError(f"no seeds in {text!r} (use e.g. 0,3 or 0-9)")
    if min(out) < 0:
        raise argparse.ArgumentTypeError(f"seeds are integers >= 0, got {min(out)} in {text!r}")
    return out


def seed_number(text: str) -> int:
    """A random seed: an integer >= 0 (numpy's generators take no negative seed)."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a seed: {text!r} (an integer >= 0)") from None
    if seed < 0:
        raise argparse.ArgumentTypeError(f"a seed is an integer >= 0, got {seed}")
    return seed


def add_world(p: argparse.ArgumentParser, default: str | None = "office", what: str = "simulator world") -> None:
    p.add_argument("--world", default=default,
                   help=f"{what}: a built-in world ({BUILTIN_WORLDS}) or a .toml world file (default: %(default)s)")


def add_worlds(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--worlds", default=default,
                   help="comma-separated built-in worlds or .toml files (default: %(default)s)")


def add_loop_closure(p: argparse.ArgumentParser, default: bool) -> None:
    p.add_argument("--loop-closure", action=argparse.BooleanOptionalAction, default=default,
                   help="run the pose graph with loop closure behind the estimator (glassmap/pose/backend.py) "
                   "(default: %(default)s)")


def add_seed(p: argparse.ArgumentParser, default: int = 0, what: str = "random seed") -> None:
    p.add_argument("--seed", type=seed_number, default=default, help=f"{what} (default: %(default)s)")


def add_seeds(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--seeds", type=parse_seeds, default=default,
                   help="seeds, comma-separated or a range a-b (default: %(default)s)")


def add_out(p: argparse.ArgumentParser, default: str | None, what: str = "output directory") -> None:
    p.add_argument("--out", default=default, help=f"{what} (default: %(default)s)")


def add_no_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_workers(p: argparse.ArgumentParser, what: str = "parallel processes") -> None:
    p.add_argument("--workers", type=int, default=0, help=f"{what}; 0 = one per core (default: %(default)s)")
