"""How stiff the pose graph's chain of sequential edges should be (`ChainConfig.chain_scale`).

Runs the front end once per world (whole route, no back end; the key scans are kept, in ``--cache`` if given)
and then

1. compares the front end's relative pose between key scans k apart with the truth, against the covariance
   of the unscaled sequential edges compounded over them: mean (error / standard deviation)^2 per axis (x
   along the first key scan's heading, sideways, heading) for k = 1, 10, 40, 160, 640 (about 6 cm of path
   per key scan); 1 = the chain is right over that span, below 1 = it claims more drift than there is;
2. runs the back end (loop closure on) on the same key scans for each ``--scales`` entry and prints the
   optimised key-scan ATE against the front end's, the graph's error at the last key scan, the closures (false
   ones: > 5 cm or 1 deg off where they constrain) and how many closures unscaled the chain;
   ``--exact-closures``: every accepted closure is replaced by the true relative pose of its two nodes, to tell
   the chain's part from the closures'.

The back end does not feed the front end, so these are the runtime's results for the same key scans.
Docs: docs/loop-closure.md, "A stiffer chain". Use validation worlds (seeds 1000-1999) or built-in ones; on
test worlds (seeds 0-99) it only reports.

Usage: .venv/bin/python scripts/chain_stiffness.py WORLD[,WORLD...] [--seed 0] [--cache DIR]
           [--scales "1,1,1;0.55,0.22,0.17"] [--exact-closures]
"""

from __future__ import annotations

import argparse
import os
import pickle
from dataclasses import replace

import numpy as np

from glassmap.pose import graph as graph_module
from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from glassmap.pose.chain import ChainConfig
from glassmap.pose.evaluate import FALSE_CLOSURE_XY, FALSE_CLOSURE_YAW, run_estimator
from glassmap.pose.motion import compose, compose_jacobians, relative
from glassmap.sim.dataset import simulate_run
from glassmap.types import wrap_angle

SPANS = (1, 10, 40, 160, 640)


def key_scans(world: str, seed: int, cache: str) -> tuple[str, list, np.ndarray]:
    """(world name, the front end's key scans, their true poses (K, 3)) of the whole default route."""
    path = os.path.join(cache, f"{os.path.basename(world).removesuffix('.toml')}-{seed}.pkl") if cache else ""
    if path and os.path.exists(path):
        with open(path, "rb") as f:
            return pickle.load(f)
    run = simulate_run(world, None, seed=seed)
    rec = GraphBackEnd(BackEndConfig(loop_closure=False))  # keeps the key scans
    traj, _ = run_estimator(run, backend=rec)
    nodes = np.minimum(np.searchsorted(traj.stamps, [k.stamp for k in rec.keys]), len(traj.stamps) - 1)
    out = (run.world_name, [replace(k, scan=None, p_glass=None) for k in rec.keys], traj.truth[nodes])
    if path:
        with open(path, "wb") as f:
            pickle.dump(out, f)
    return out


def span_ratios(keys: list, truth: np.ndarray) -> dict[int, np.ndarray]:
    """Per span k: mean (error / sigma)^2 (3,) of the front end's relative pose over k key scans against the
    unscaled sequential edges compounded over them."""
    be = GraphBackEnd(BackEndConfig(chain=ChainConfig(chain_scale=(1.0, 1.0, 1.0)), loop_closure=False))
    for k in keys:
        be.add(k)
    front = np.array([k.pose for k in keys])
    out = {}
    for span in SPANS:
        ratios = []
        for i in range(0, len(keys) - span, max(1, span // 4)):
            cov, rel = np.zeros((3, 3)), np.zeros(3)
            for j in range(i, i + span):
                e = be.graph.edges[j]
                ja, jb = compose_jacobians(rel, e.rel)
                cov = ja @ cov @ ja.T + jb @ e.cov @ jb.T
                rel = compose(rel, e.rel)
            err = relative(front[i], front[i + span]) - relative(truth[i], truth[i + span])
            err[2] = float(wrap_angle(err[2]))
            ratios.append(err ** 2 / np.diag(cov))
        if ratios:
            out[span] = np.mean(ratios, axis=0)
    return out


def run_back_end(keys: list, truth: np.ndarray, scale: tuple[float, float, float], exact: bool) -> dict:
    """The back end on the recorded key scans with ``chain_scale`` = scale."""
    add_loop = graph_module.PoseGraph.add_loop
    if exact:
        graph_module.PoseGraph.add_loop = (
            lambda self, a, b, rel, cov: add_loop(self, a, b, relative(truth[a], truth[b]), cov))
    try:
        be = GraphBackEnd(BackEndConfig(chain=ChainConfig(chain_scale=scale)))
        for k in keys:
            be.add(k)
    finally:
        graph_module.PoseGraph.add_loop = add_loop
    front = np.array([k.pose for k in keys])
    opt = be.poses()
    e_front = np.hypot(*(front[:, :2] - truth[:, :2]).T)
    e_opt = np.hypot(*(opt[:, :2] - truth[:, :2]).T)
    errs = np.array([c.error(truth[c.anchor], truth[c.node]) for c in be.closures]).reshape(-1, 2)
    return dict(front=100 * np.sqrt(np.mean(e_front ** 2)), opt=100 * np.sqrt(np.mean(e_opt ** 2)),
                end=100 * e_opt[-1], closures=len(be.closures), unscaled=be.chain_unscaled,
                false=int(np.sum((errs[:, 0] > FALSE_CLOSURE_XY) | (errs[:, 1] > FALSE_CLOSURE_YAW))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", help="comma-separated built-in world names or .toml world files")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default="", help="directory that keeps each world's key scans between runs")
    ap.add_argument("--scales", default=";".join(",".join(f"{v:g}" for v in s) for s in
                                                 ((1.0, 1.0, 1.0), ChainConfig().chain_scale)),
                    help="chain_scale values to compare: 'x,y,yaw;x,y,yaw;...'")
    ap.add_argument("--exact-closures", action="store_true", help="replace each closure by the true relative pose")
    args = ap.parse_args()
    if args.cache:
        os.makedirs(args.cache, exist_ok=True)
    scales = [tuple(float(v) for v in s.split(",")) for s in args.scales.split(";")]
    results: dict[tuple, list[dict]] = {s: [] for s in scales}
    for world in args.worlds.split(","):
        name, keys, truth = key_scans(world, args.seed, args.cache)
        ratios = span_ratios(keys, truth)
        print(f"{name}: {len(keys)} key scans; (error / sigma)^2 of the unscaled chain, x / sideways / heading: "
              + "; ".join(f"k={k} {r[0]:.3f} / {r[1]:.3f} / {r[2]:.3f}" for k, r in ratios.items()), flush=True)
        for s in scales:
            r = run_back_end(keys, truth, s, args.exact_closures)
            results[s].append(r)
            print(f"  chain_scale {s}: front end ATE {r['front']:.2f} cm, optimised {r['opt']:.2f} cm, graph end "
                  f"{r['end']:.2f} cm; {r['closures']} closures ({r['false']} false), {r['unscaled']} unscaled "
                  "the chain", flush=True)
    for s, rs in results.items():
        opt, front = np.array([r["opt"] for r in rs]), np.array([r["front"] for r in rs])
        print(f"chain_scale {s}: optimised ATE mean {opt.mean():.2f} cm (front end {front.mean():.2f}), worse than "
              f"the front end on {int(np.sum(opt > front))} of {len(rs)}, worst ratio {np.max(opt / front):.2f}; graph "
              f"end mean {np.mean([r['end'] for r in rs]):.2f} cm; false closures {sum(r['false'] for r in rs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
