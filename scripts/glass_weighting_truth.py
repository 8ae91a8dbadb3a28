"""What glass-aware matching down-weights, against the simulator's truth: at every key-scan match of a run with
the runtime's online glass map (``glassmap pose eval --glass-weighting online``), the matched beams that
``PoseEstimator.glass_weights`` gives a weight below 1, split by what each beam really returned: a mirror image
(ghost), a real surface seen through a pane, the pane itself, anything else. Also, per kind of beam, how often its
path (short of the last ``glass_behind_margin``) crosses a cell the occupancy grid holds as occupied, and for the
ghosts how often the glass layer has any glass evidence along their path (docs/pose.md, "What the runtime's
glass-aware matching down-weights").

Usage: .venv/bin/python scripts/glass_weighting_truth.py WORLD [--seed 0] [--route default] [--cache DIR]
           [--set field=value ...]

A diagnostic: nothing is chosen from it on test worlds (seeds 0-99), only reported. ``--cache`` and ``--set`` as in
scripts/pose_consistency.py (same file names, so its cached runs are reused).
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pose_consistency import _config, load_run  # noqa: E402

from glassmap.cli_args import seed_number  # noqa: E402
from glassmap.classifier import GlassClassifier  # noqa: E402
from glassmap.pose import estimator as est_mod  # noqa: E402
from glassmap.pose.evaluate import run_estimator  # noqa: E402
from glassmap.sim.world import WorldFileError, load_world  # noqa: E402

KINDS = ("mirror ghost", "real surface through a pane", "the pane itself", "anything else")


def _path_maxima(grid, layer: np.ndarray, laser_pose: np.ndarray, angles: np.ndarray, reach: np.ndarray
                 ) -> np.ndarray:
    """Per beam, the largest value of ``layer`` (grid-shaped) at quarter-cell samples of its path short of
    ``reach`` (m); -inf where the path has no sample on the grid."""
    t = np.arange(0.0, float(reach.max(initial=0.0)) + grid.resolution, 0.25 * grid.resolution)
    a = laser_pose[2] + angles
    cx = np.floor((laser_pose[0] + np.cos(a)[:, None] * t - grid.origin[0]) / grid.resolution).astype(np.int64)
    cy = np.floor((laser_pose[1] + np.sin(a)[:, None] * t - grid.origin[1]) / grid.resolution).astype(np.int64)
    h, w = layer.shape
    ok = (t[None, :] < reach[:, None]) & (cx >= 0) & (cy >= 0) & (cx < w) & (cy < h)
    vals = np.where(ok, layer[np.clip(cy, 0, h - 1), np.clip(cx, 0, w - 1)], -np.inf)
    return vals.max(axis=1) if vals.size else np.full(angles.size, -np.inf)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world")
    ap.add_argument("--seed", type=seed_number, default=0)
    ap.add_argument("--route", default="default", help="route name, or 'default'")
    ap.add_argument("--cache", default="")
    ap.add_argument("--set", action="append", default=[], help="EstimatorConfig field=value")
    args = ap.parse_args()
    try:
        world = load_world(args.world)
    except WorldFileError as e:
        raise SystemExit(f"error: {e}") from None
    cfg = replace(_config(args.set), glass_weighting=True)
    stem = os.path.splitext(os.path.basename(args.world))[0]
    run = load_run(args.world, args.route, args.seed, args.cache)
    if run.is_ghost is None:
        raise SystemExit("error: this run was simulated without mirror images (no ghost truth to compare with)")
    geo = run.geometry
    records: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    scan = {"i": -1}
    update, weights = est_mod.PoseEstimator.update, est_mod.PoseEstimator.glass_weights

    def counting_update(self, *a, **k):
        scan["i"] += 1
        return update(self, *a, **k)

    def recording_weights(self, laser_pose, angles, ranges):
        w = weights(self, laser_pose, angles, ranges)
        g = self.occupancy.grid
        r = np.where(np.isfinite(ranges), ranges, 0.0)
        glass = _path_maxima(g, g[est_mod.GLASS_LAYER], laser_pose, angles, r)
        occ = _path_maxima(g, self.occupancy.log_odds, laser_pose, angles,
                           r - self.config.glass_behind_margin)
        beams = np.rint((angles - geo.angle_min) / geo.angle_increment).astype(np.int64)
        records.append((scan["i"], beams, w, glass, occ))
        return w

    est_mod.PoseEstimator.update, est_mod.PoseEstimator.glass_weights = counting_update, recording_weights
    try:
        run_estimator(run, cfg, world=world, glass_online=True, classifier=GlassClassifier.load_default())
    finally:
        est_mod.PoseEstimator.update, est_mod.PoseEstimator.glass_weights = update, weights
    counts = np.zeros((len(KINDS), 2), np.int64)
    occupied = [[] for _ in KINDS]
    ghost_glass = []
    for i, b, w, glass, occ in records:
        gh = run.is_ghost[i, b]
        through = run.crossed_glass[i, b].astype(bool) & ~gh
        pane = run.is_glass[i, b].astype(bool) & ~gh & ~through
        for k, m in enumerate((gh, through, pane, ~(gh | through | pane))):
            counts[k] += (int(m.sum()), int((m & (w < 1.0)).sum()))
            occupied[k].append(occ[m])
        ghost_glass.append(glass[gh])
    total, down = int(counts[:, 0].sum()), int(counts[:, 1].sum())
    occ_lo = cfg.likelihood.occupied_log_odds
    print(f"{stem} seed {args.seed}: {len(records)} key-scan matches, {total} matched beams, {down} down-weighted "
          f"({100 * down / max(total, 1):.1f} %)")
    for k, name in enumerate(KINDS):
        n, d = counts[k]
        o = np.concatenate(occupied[k])
        print(f"  {name:28s} {n:8d} beams, {d:7d} down-weighted ({100 * d / max(n, 1):5.1f} %; "
              f"{100 * d / max(down, 1):5.1f} % of the down-weighted); path crosses an occupied cell: "
              f"{100 * np.mean(o > occ_lo) if o.size else float('nan'):5.1f} %")
    gg = np.concatenate(ghost_glass)
    if gg.size:
        print(f"  ghosts with any glass evidence (log-odds > 0) along their path: {100 * np.mean(gg > 0):.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
