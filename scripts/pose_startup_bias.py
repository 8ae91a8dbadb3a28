"""Along-track error of the pose estimate over the first seconds of a run, under variants of the simulation
and the estimator: where the start-up bias comes from (docs/pose.md, "Start-up bias").

Usage: .venv/bin/python scripts/pose_startup_bias.py WORLD [--seconds 20] [--seed 0]
           [--variants default,perfect-odometry,no-mirror,no-range-noise,every-scan,sigma-hit-5cm,
                       field-every-1,field-every-2,field-every-10,field-incremental]

Prints, per variant, the mean along-track error (estimate minus truth, m -> cm, positive = ahead) over the
second half of the window and at its end. Use validation worlds (seeds 1000-1999), never test worlds.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import replace

import numpy as np

from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import run_estimator
from glassmap.sim.dataset import simulate_run
from glassmap.sim.laser import world_laser_params
from glassmap.sim.robot import OdometryNoise
from glassmap.sim.world import load_world

VARIANTS = ("default", "perfect-odometry", "no-mirror", "no-range-noise", "every-scan", "sigma-hit-5cm",
            "field-every-1", "field-every-2", "field-every-10", "field-incremental")


def _first(run, seconds: float):
    n = int(np.searchsorted(run.scan_stamps, seconds))
    return dataclasses.replace(run, scan_stamps=run.scan_stamps[:n], ranges=run.ranges[:n],
                               intensities=run.intensities[:n], scan_true_poses=run.scan_true_poses[:n],
                               laser_poses=run.laser_poses[:n])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--route", default="short")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args()
    world = load_world(args.world)
    laser = world_laser_params(world)
    sim = {"perfect-odometry": dict(odom_noise=OdometryNoise.none()),
           "no-mirror": dict(laser_params=replace(laser, mirror_reflections=False)),
           "no-range-noise": dict(laser_params=replace(laser, range_noise=0.0, range_noise_slope=0.0))}
    base = EstimatorConfig()
    est = {"every-scan": replace(base, keyframe_distance=0.0, keyframe_angle=0.0),
           "sigma-hit-5cm": replace(base, likelihood=replace(base.likelihood, sigma_hit=0.05)),
           "field-every-1": replace(base, field_refresh_scans=1),
           "field-every-2": replace(base, field_refresh_scans=2),
           "field-every-10": replace(base, field_refresh_scans=10),
           "field-incremental": replace(base, field_incremental=True)}
    runs: dict[str, object] = {}
    for name in args.variants.split(","):
        if name not in VARIANTS:
            raise SystemExit(f"unknown variant {name!r}; variants: {', '.join(VARIANTS)}")
        key = name if name in sim else "default"
        if key not in runs:
            runs[key] = _first(simulate_run(world, args.route, seed=args.seed, **sim.get(key, {})), args.seconds)
        traj, _ = run_estimator(runs[key], est.get(name, base), world=world)
        e = traj.poses - traj.truth
        th = traj.truth[:, 2]
        along = np.cos(th) * e[:, 0] + np.sin(th) * e[:, 1]
        late = traj.stamps > args.seconds / 2
        print(f"{name:18s} along-track error: mean over the second half {100 * along[late].mean():+6.2f} cm, "
              f"at the end {100 * along[-1]:+6.2f} cm", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
