"""Covariance consistency of the pose estimator over many runs: mean NEES and the share of scans inside the
95 % bound per run, their distribution, the worst world, and how many runs are in the target band
(mean NEES in [1.5, 6] and >= 85 % inside). Settings are chosen with it on VALIDATION worlds (generated
seeds 1000-1999); on test worlds (seeds 0-99) it only reports.

Usage: .venv/bin/python scripts/pose_consistency.py WORLD.toml[,WORLD.toml...] [--seeds 0-2] [--route short]
           [--set map_uncertainty=off] [--glass-online] [--drop-ghosts] [--workers 1] [--cache DIR] [--out runs.csv]

``--set`` overrides EstimatorConfig fields (numbers, booleans or words; nested ones dotted: matcher.voxel=0.1);
``--glass-online`` builds the glass map as the runtime does (classifier + glass mapper at the estimated poses) and
turns glass-aware matching on (``glass_weighting``; its other fields with ``--set``), as ``glassmap pose eval
--glass-weighting online``; ``--drop-ghosts`` removes every mirror-image return (the simulator's truth) before the
estimator sees the run: a perfect ghost detector, for comparison;
``--cache`` keeps the simulated runs as .npz files so that variants of the estimator are compared on the same
runs without simulating again.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import fields, replace

import numpy as np

from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import metrics, run_estimator
from glassmap.sim.world import WorldFileError, load_world

NEES_BAND = (1.5, 6.0)
INSIDE_MIN = 0.85


def _config(sets: list[str]) -> EstimatorConfig:
    cfg = EstimatorConfig()
    for kv in sets:
        k, v = kv.split("=", 1)
        cfg = _override(cfg, k.split("."), v)
    return cfg


def _override(obj, path: list[str], value: str):
    """The dataclass ``obj`` with the field ``path`` (nested: ["matcher", "voxel"]) set to ``value`` (a number,
    a boolean, a string, or numbers separated by commas for a tuple)."""
    name = path[0]
    if name not in {f.name for f in fields(obj)}:
        raise SystemExit(f"no {type(obj).__name__} field {name!r}")
    cur = getattr(obj, name)
    if len(path) > 1:
        return replace(obj, **{name: _override(cur, path[1:], value)})
    if isinstance(cur, bool):
        new = value.lower() in ("1", "true", "yes")
    elif isinstance(cur, tuple):
        new = tuple(float(v) for v in value.split(","))
    else:
        new = value if isinstance(cur, str) else type(cur)(float(value))
    return replace(obj, **{name: new})


def load_run(world, route: str, seed: int, cache: str):
    """The simulated run of ``world`` (a name, a path or a World; ``route`` a name or "default"), read from the
    ``cache`` directory (``<world file stem>-<route>-<seed>.npz``) if there, else simulated (and saved there)."""
    from glassmap.sim.dataset import SimRun, simulate_run

    path = ""
    if cache:
        stem = os.path.splitext(os.path.basename(str(world)))[0]
        path = os.path.join(cache, f"{stem}-{route}-{seed}.npz")
        if os.path.exists(path):
            return SimRun.load(path)
    run = simulate_run(world, None if route == "default" else route, seed=seed)
    if path:
        os.makedirs(cache, exist_ok=True)
        run.save(path)
    return run


def _one(job: tuple) -> dict:
    world, route, seed, sets, cache, glass_online, drop_ghosts = job
    run = load_run(world, route, seed, cache)
    if drop_ghosts and run.is_ghost is not None:
        run.ranges[run.is_ghost] = np.nan
    t = time.perf_counter()
    cfg, clf = _config(sets), None
    if glass_online:
        from glassmap.classifier import GlassClassifier

        cfg, clf = replace(cfg, glass_weighting=True), GlassClassifier.load_default()
    traj, _ = run_estimator(run, cfg, world=world, glass_online=glass_online, classifier=clf)
    m = metrics(traj, run).as_dict()
    m["seconds"] = time.perf_counter() - t
    return m


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--route", default="short", help="route name, or 'default'")
    ap.add_argument("--set", action="append", default=[], help="EstimatorConfig field=value")
    ap.add_argument("--glass-online", action="store_true", help="online glass map + glass-aware matching")
    ap.add_argument("--drop-ghosts", action="store_true", help="remove the mirror-image returns (simulator's truth)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--cache", default="")
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    _config(args.set)  # fail early on a bad override
    try:  # and on a world that does not load (in a worker it would break the pool)
        for w in args.worlds.split(","):
            load_world(w)
    except WorldFileError as e:
        raise SystemExit(f"error: {e}") from None
    jobs = [(w, args.route, s, args.set, args.cache, args.glass_online, args.drop_ghosts)
            for w in args.worlds.split(",") for s in _seeds(args.seeds)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(_one, jobs))
    for r in rows:
        ok = NEES_BAND[0] <= r["nees_mean"] <= NEES_BAND[1] and r["inside_95"] >= INSIDE_MIN
        print(f"{r['world']:22s} seed {r['seed']:2d}  ATE {100 * r['ate_rmse']:5.2f} cm  NEES {r['nees_mean']:6.2f}  "
              f"inside {100 * r['inside_95']:5.1f} %  (key {r['nees_key_mean']:5.2f} "
              f"between {r['nees_between_mean']:5.2f}; yaw {r['yaw_nees_key_mean']:4.2f} "
              f"{r['yaw_nees_between_mean']:4.2f}; axes {r['along_nees_mean']:4.2f} {r['cross_nees_mean']:4.2f} "
              f"{r['yaw_nees_mean']:4.2f})  sigma {100 * r['sigma_xy_mean']:5.2f} cm  "
              f"{'in band' if ok else 'OUT'}", flush=True)
    _summary(rows)
    print(f"{time.perf_counter() - t0:.0f} s")
    if args.out:
        with open(args.out, "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=list(rows[0]))
            wr.writeheader()
            wr.writerows(rows)
    return 0


def _summary(rows: list[dict]) -> None:
    nk, ik = "nees_mean", "inside_95"
    nees = np.array([r[nk] for r in rows])
    inside = np.array([r[ik] for r in rows])
    band = (nees >= NEES_BAND[0]) & (nees <= NEES_BAND[1]) & (inside >= INSIDE_MIN)
    q = np.percentile(nees, [0, 25, 50, 75, 100])
    print(f"{len(rows)} runs, {band.sum()} in band; mean NEES min {q[0]:.2f} "
          f"quartiles {q[1]:.2f} / {q[2]:.2f} / "
          f"{q[3]:.2f} max {q[4]:.2f}; inside the 95 % bound min {100 * inside.min():.0f} % median "
          f"{100 * np.median(inside):.0f} %; too wide (NEES < {NEES_BAND[0]}): {(nees < NEES_BAND[0]).sum()}, "
          f"too narrow (NEES > {NEES_BAND[1]} or < {100 * INSIDE_MIN:.0f} % inside): "
          f"{((nees > NEES_BAND[1]) | (inside < INSIDE_MIN)).sum()}; "
          f"ATE mean {100 * np.mean([r['ate_rmse'] for r in rows]):.2f} cm")
    key = np.array([r["nees_key_mean"] for r in rows])
    between = np.array([r["nees_between_mean"] for r in rows])
    print(f"mean NEES of the key scans: min {np.nanmin(key):.2f} median {np.nanmedian(key):.2f} "
          f"max {np.nanmax(key):.2f}; "
          f"of the scans between them: min {np.nanmin(between):.2f} median {np.nanmedian(between):.2f} "
          f"max {np.nanmax(between):.2f}")
    axes = [(name, np.array([r[k] for r in rows])) for name, k in
            (("along the track", "along_nees_mean"), ("across", "cross_nees_mean"), ("heading", "yaw_nees_mean"))]
    print("each axis alone (ideal 1): " + "; ".join(f"{name} min {a.min():.2f} median {np.median(a):.2f} max "
                                                    f"{a.max():.2f}" for name, a in axes))
    worlds = sorted({r["world"] for r in rows})
    per = [(w, np.mean([r[nk] for r in rows if r["world"] == w]), np.mean([r[ik] for r in rows if r["world"] == w]))
           for w in worlds]
    worst = max(per, key=lambda p: abs(np.log(p[1] / 3.0)))
    print(f"worst world (mean over seeds): {worst[0]} NEES {worst[1]:.2f}, inside {100 * worst[2]:.0f} %")


if __name__ == "__main__":
    raise SystemExit(main())
