"""How far the end points of registered key scans really are from where the map holds their surface, beside
the registration sigma the runtime gives them (is the sigma of eq. 3 honest?).

For every key scan the estimator writes into its map (run seed 0, whole default route), each beam that hit its
true surface (first echo within 10 cm of the true range, up to 15 m): its end point at the estimated pose minus
the true surface point is its absolute error; the map's error there is the mean absolute error of the earlier
end points that fell in the 3 x 3 cells around it; the difference is the error relative to the map, which is
what registration onto the nearest occupied cell sees. Printed: its rms per axis, median and p90 length, the
share over half a cell, the median registration sigma (``online_sigma(..., "map")``, the runtime's) and the mean
of |e|^2 / (2 sigma^2) (1 for an honest isotropic sigma; below 1: the sigma is wide).

Usage: .venv/bin/python scripts/registration_error.py WORLD[,WORLD...] [--route NAME] [--seed 0]
Use validation worlds (seeds 1000-1999) or built-in ones; on test worlds (seeds 0-99) it only reports.
"""

from __future__ import annotations

import argparse

import numpy as np

from glassmap.pose.corrected import online_sigma
from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import run_estimator
from glassmap.sim.dataset import simulate_run

CELL = 0.05  # m, the map's cells
SIZE = 3000  # cells each way of the bookkeeping grid (150 m), centred on the start


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", help="comma-separated built-in world names or .toml world files")
    ap.add_argument("--route", default=None, help="route name (default: the world's default route)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for world in args.worlds.split(","):
        run = simulate_run(world, args.route, seed=args.seed)
        angles = run.geometry.angles
        origin = run.laser_poses[0, :2] - SIZE * CELL / 2
        sums = np.zeros((3, SIZE, SIZE))  # per cell: sum of x errors, of y errors, count
        rel_all, sig_all = [], []

        def on_scan(i, scan, estimate, est):
            if not (est.stats.last_keyframe and est.last_key_scan is not None and est.last_key_scan.written):
                return
            r = np.asarray(scan.ranges, dtype=np.float64)
            tr = run.true_range[i].astype(np.float64)
            ok = np.isfinite(r) & np.isfinite(tr) & (r < 15.0) & (np.abs(r - tr) < 0.1)
            lp, tl, a = est.laser_pose_of(est.scan_pose()), run.laser_poses[i], angles[ok]
            end = lp[:2] + r[ok, None] * np.stack([np.cos(lp[2] + a), np.sin(lp[2] + a)], axis=1)
            true_end = tl[:2] + tr[ok, None] * np.stack([np.cos(tl[2] + a), np.sin(tl[2] + a)], axis=1)
            err = end - true_end
            sig = online_sigma(est, estimate, r, "map")[ok]
            c = np.floor((end - origin) / CELL).astype(int)
            inside = np.all((c >= 1) & (c < SIZE - 1), axis=1)
            c, err, sig = c[inside], err[inside], sig[inside]
            pooled = sum(sums[:, c[:, 1] + dy, c[:, 0] + dx] for dx in (-1, 0, 1) for dy in (-1, 0, 1))
            known = pooled[2] > 0
            rel_all.append(err[known] - (pooled[:2, known] / pooled[2, known]).T)
            sig_all.append(sig[known])
            for k, v in enumerate((err[:, 0], err[:, 1], np.ones(len(err)))):
                np.add.at(sums[k], (c[:, 1], c[:, 0]), v)

        run_estimator(run, EstimatorConfig(), on_scan=on_scan)
        rel, sig = np.concatenate(rel_all), np.concatenate(sig_all)
        length = np.hypot(rel[:, 0], rel[:, 1])
        z = np.sum(rel ** 2, axis=1) / (2 * sig ** 2)
        print(f"{run.world_name}: {len(length)} end points; error relative to the map: rms "
              f"{100 * np.sqrt(np.mean(length ** 2) / 2):.2f} cm per axis, median {100 * np.median(length):.2f} cm, "
              f"p90 {100 * np.percentile(length, 90):.2f} cm, {100 * np.mean(length > CELL / 2):.1f} % over half a "
              f"cell; registration sigma median {100 * np.median(sig):.2f} cm; mean |e|^2 / (2 sigma^2) "
              f"{z.mean():.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
