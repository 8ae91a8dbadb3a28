"""Loop closure with submaps of different lengths (`SubmapConfig.length`), against the truth.

A closure matches the current key scan against old submaps placed by the pose graph; each submap is built at
the front end's poses relative to its first key scan, so the front end's drift inside a submap is not in the
graph and the closure inherits it (docs/loop-closure.md, "Shorter submaps").

Usage: .venv/bin/python scripts/submap_length.py WORLD[,WORLD...] [--lengths 4,2,1] [--seed 0] [--true-submaps]

Per world and length (whole default route): closures accepted (full = constraining all three directions) and
false ones (> 5 cm or 1 deg off where they constrain), the full closures' rms error and the worst closure error
where it constrains, the estimate the runtime reports at the end (the front end's corrected by the graph,
``corrected_estimate``) in cm and in sigma (xy Mahalanobis), the optimised key-scan ATE and the graph's error at
the last key scan, and the back end's time per key scan. ``--true-submaps``: also match each accepted closure's
key scan again against its submaps built at the true poses, to tell the submaps' own error from the match's.
Use validation worlds (seeds 1000-1999) or built-in ones; on test worlds (seeds 0-99) it only reports.
"""

from __future__ import annotations

import argparse
import copy
import time
from dataclasses import replace

import numpy as np

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import FALSE_CLOSURE_XY, FALSE_CLOSURE_YAW, run_estimator
from glassmap.pose.motion import relative
from glassmap.pose.submaps import SubmapConfig, SubmapStore
from glassmap.sim.dataset import simulate_run


def _rematch(be: GraphBackEnd, truth: np.ndarray, true_poses: bool) -> list[float]:
    """Each accepted closure's key scan matched again against its nearest old submaps, built at the front
    end's poses (placed by the graph's solution) or at the true poses: the match's error (m) against the
    truth."""
    store = SubmapStore(be.submaps.config)
    store.submaps = copy.deepcopy(be.submaps.submaps)
    poses = truth if true_poses else be.poses()
    if true_poses:
        for sm in store.submaps:
            sm.local = [relative(truth[sm.anchor], truth[n]) for n in sm.nodes]
    out = []
    for c in be.closures:
        group = be.closer.select_submaps(store, poses, c.node, be.travel[c.node])
        if not group:
            continue
        a = group[0].anchor
        res, _, _ = be.closer.match(store, group, poses, be.keys[c.node], relative(poses[a], poses[c.node]),
                                    be.travel[c.node])
        if res is not None:
            e = relative(truth[a], truth[c.node]) - res.pose
            out.append(float(np.hypot(e[0], e[1])))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", help="comma-separated built-in world names or .toml world files")
    ap.add_argument("--lengths", default="4,2,1", help="submap lengths (m of travel), comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--true-submaps", action="store_true",
                    help="also match the closures again against submaps built at the true poses")
    args = ap.parse_args()
    for world in args.worlds.split(","):
        run = simulate_run(world, None, seed=args.seed)
        for length in (float(x) for x in args.lengths.split(",")):
            cfg = BackEndConfig(submaps=replace(SubmapConfig(), length=length))
            be = GraphBackEnd(cfg)
            add, seconds = be.add, []

            def timed(key, add=add, seconds=seconds):
                t0 = time.perf_counter()
                out = add(key)
                seconds.append(time.perf_counter() - t0)
                return out

            be.add = timed
            traj, _ = run_estimator(run, EstimatorConfig(), backend=be)
            nodes = np.minimum(np.searchsorted(traj.stamps, [k.stamp for k in be.keys]), len(traj.stamps) - 1)
            truth = traj.truth[nodes]
            errs = np.array([c.error(truth[c.anchor], truth[c.node]) for c in be.closures]).reshape(-1, 2)
            full = np.array([np.allclose(c.proj, np.eye(3)) for c in be.closures], dtype=bool)
            false = int(np.sum((errs[:, 0] > FALSE_CLOSURE_XY) | (errs[:, 1] > FALSE_CLOSURE_YAW)))
            d = (traj.corrected[-1] - traj.truth[-1])[:2]  # the corrected estimate at the end
            sigma = float(np.sqrt(d @ np.linalg.solve(traj.corrected_covs[-1][:2, :2], d)))
            graph = np.hypot(*(be.poses()[:, :2] - truth[:, :2]).T)
            ms = 1e3 * np.asarray(seconds)
            full_rms = 100 * np.sqrt(np.mean(errs[full, 0] ** 2)) if full.any() else float("nan")
            worst = 100 * errs[:, 0].max() if len(errs) else float("nan")
            print(f"{run.world_name} submaps {length:g} m: {len(be.closures)} closures ({full.sum()} full, {false} "
                  f"false), full rms {full_rms:.2f} cm, worst {worst:.2f} cm where it constrains; at the end "
                  f"{100 * np.hypot(*d):.2f} cm, {sigma:.1f} sigma; optimised ATE {100 * np.sqrt(np.mean(graph ** 2)):.2f}"
                  f" cm, graph end {100 * graph[-1]:.2f} cm; back end {ms.mean():.2f} ms per key scan (max {ms.max():.0f})",
                  flush=True)
            if args.true_submaps and be.closures:
                for name, tp in (("front-end poses", False), ("true poses", True)):
                    e = 100 * np.asarray(_rematch(be, truth, tp))
                    print(f"  closures matched again against submaps at the {name}: rms {np.sqrt(np.mean(e ** 2)):.2f} "
                          f"cm, worst {e.max():.2f} cm", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
