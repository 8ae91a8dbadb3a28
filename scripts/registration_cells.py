"""Which blueprint cells robust 3x3 registration labels differently from direct on online trials, and what
lies around them (docs/loop-closure.md, "Where robust 3x3's online margin comes from").

For each seed: one online trial (`glassmap pose experiment`'s, poses and registration sigma from the
estimator), then per blueprint class (glass, wall) the scored cells each method labels right, the cells only
direct labels right ("lost" by robust 3x3) and only robust 3x3 ("gained"), and for those, the share with a
cell of the other class (wall for glass cells, glass for wall cells) among their 8 neighbours in the
blueprint, beside that share over all scored cells of the class.

    python scripts/registration_cells.py WORLD.toml [--seeds 0-1] [--route loop]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import binary_dilation

from glassmap.cli_args import add_seeds
from glassmap.pose.experiment import OnlineTrialConfig, run_online_trial

WALL, GLASS = 1, 2


def report(maps: dict) -> list[str]:
    truth, scored = maps["truth"], maps["evaluated"]
    direct, robust = maps["direct"], maps["robust3"]
    lines = []
    for cls, other, name, other_name, right in ((GLASS, WALL, "glass", "a wall", 1), (WALL, GLASS, "wall", "glass", 0)):
        near = binary_dilation(truth == other, structure=np.ones((3, 3), bool))  # an 8-neighbour of the other class
        cells = scored & (truth == cls)
        d_ok, r_ok = cells & (direct == right), cells & (robust == right)
        lines.append(f"  {name}: {cells.sum()} cells scored (next to {other_name} {near[cells].mean():.0%}); right: "
                     f"direct {d_ok.sum()}, robust3 {r_ok.sum()}")
        for label, sel in (("lost by robust3", d_ok & ~r_ok), ("gained by robust3", r_ok & ~d_ok)):
            if sel.any():
                lines.append(f"    {label}: {sel.sum()} (next to {other_name} {near[sel].mean():.0%})")
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
