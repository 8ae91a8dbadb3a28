"""Which blueprint cells robust 3x3 registration labels differently from direct on online trials, and what
lies around them (docs/loop-closure.md, "Where robust 3x3's online margin comes from").

For each seed: one online trial (`glassmap pose experiment`'s, poses and registration sigma from the
estimator), then per blueprint class (glass, wall) the scored cells each method labels right, the cells only
direct labels right ("lost" by robust 3x3) and only robust 3x3 ("gained"), and for those, the share with a
wall cell and with a glass cell among their 8 neighbours in the blueprint, beside that share over all
scored cells of the class.

    python scripts/registration_cells.py WORLD.toml [--seeds 0-1] [--route loop]
"""

from __future__ import annotations

import argparse

import numpy as np

from glassmap.cli_args import add_seeds
from glassmap.pose.experiment import OnlineTrialConfig, run_online_trial

WALL, GLASS = 1, 2


def neighbours(mask: np.ndarray) -> np.ndarray:
    """How many of each cell's 8 neighbours are set in ``mask`` (H, W) bool."""
    p = np.pad(mask, 1).astype(np.int64)
    h, w = mask.shape
    return sum(p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)


def report(maps: dict) -> list[str]:
    truth, scored = maps["truth"], maps["evaluated"]
    direct, robust = maps["direct"], maps["robust3"]
    near_wall, near_glass = neighbours(truth == WALL) > 0, neighbours(truth == GLASS) > 0
    lines = []
    for cls, name, right in ((GLASS, "glass", 1), (WALL, "wall", 0)):
        cells = scored & (truth == cls)
        d_ok, r_ok = cells & (direct == right), cells & (robust == right)
        lines.append(f"  {name}: {cells.sum()} cells scored (next to a wall {near_wall[cells].mean():.0%}, next to "
                     f"glass {near_glass[cells].mean():.0%}); right: direct {d_ok.sum()}, robust3 {r_ok.sum()}")
        for label, sel in (("lost by robust3", d_ok & ~r_ok), ("gained by robust3", r_ok & ~d_ok)):
            if sel.any():
                lines.append(f"    {label}: {sel.sum()} (next to a wall {near_wall[sel].mean():.0%}, next to glass "
                             f"{near_glass[sel].mean():.0%})")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("world", help="a world file (.toml) or a built-in world")
    add_seeds(ap, "0-1")
    ap.add_argument("--route", default="loop", help="route (default: %(default)s)")
    a = ap.parse_args()
    cfg = OnlineTrialConfig(world=a.world, route=a.route, methods=("direct", "robust3"))
    for seed in a.seeds:
        maps: dict = {}
        rows = {r["method"]: r for r in run_online_trial(cfg, seed, maps_out=maps)}
        d, r = rows["direct"], rows["robust3"]
        print(f"seed {seed}: error direct {d['error']:.4f}, robust3 {r['error']:.4f}; glass recall "
              f"{d['glass_recall']:.3f} / {r['glass_recall']:.3f}; false glass {d['false_glass_rate']:.3f} / "
              f"{r['false_glass_rate']:.3f}")
        print("\n".join(report(maps)))


if __name__ == "__main__":
    main()
