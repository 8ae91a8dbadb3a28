"""Consistency of the pose graph's online estimate and covariance beside the front end's, against the truth.

Every 10th key scan: the newest node's iSAM2 estimate and marginal covariance when it is added (what the back
end knows at that moment), and the front end's estimate and reported covariance at the same scan
(docs/loop-closure.md, "The back end's covariance"). Every 40th scan and the last: the front end's estimate
and the corrected estimate the runtime reports with loop closure on (``corrected_estimate``: moved by the
latest correction, with the newest node's marginal carried to the scan).

Usage: .venv/bin/python scripts/graph_consistency.py WORLD[,WORLD...] [--seed 0] [--route default]
           [--backend match_scale=0.05,min_sigma=0.001:0.001:0.0005] [--closures]

Prints per run the loop closures, and for the graph, the front end and the corrected estimate: mean NEES
(x, y, yaw), the share of checks inside the 95 % bound, the NEES of the last check (the end of the route) and
the rms position error; with ``--closures`` also each accepted closure's error against the truth (whole,
and in the directions it constrains).
Use validation worlds (seeds 1000-1999) or built-in ones; on test worlds (seeds 0-99) it only reports.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from glassmap.pose.estimator import EstimatorConfig
from glassmap.pose.evaluate import CHI2_3DOF_95, run_estimator
from glassmap.pose.motion import relative
from glassmap.sim.dataset import simulate_run
from glassmap.types import wrap_angle


def _nees(err: np.ndarray, cov: np.ndarray) -> float:
    e = err.copy()
    e[2] = float(wrap_angle(e[2]))
    return float(e @ np.linalg.solve(cov, e))


def _line(name: str, nees: list[float], err: list[float]) -> str:
    n = np.array(nees)
    return (f"{name}: mean NEES {n.mean():.2f}, inside 95 % {100 * np.mean(n < CHI2_3DOF_95):.0f} %, last {n[-1]:.1f}, "
            f"error rms {100 * np.sqrt(np.mean(np.square(err))):.2f} cm")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", help="comma-separated built-in world names or .toml world files")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--route", default="default", help="route name, or 'default'")
    ap.add_argument("--closures", action="store_true", help="print each accepted closure's error against the truth")
    ap.add_argument("--backend", default="", help="BackEndConfig overrides, e.g. match_scale=0.05,min_sigma=0.001:0.001:0.0005 (a tuple's values joined by ':')")
    args = ap.parse_args()
    cfg = EstimatorConfig()
    backend_cfg = BackEndConfig()
    for kv in filter(None, args.backend.split(",")):
        k, v = kv.split("=")
        in_chain = hasattr(backend_cfg.chain, k)  # the sequential edges' settings
        cur = getattr(backend_cfg.chain if in_chain else backend_cfg, k)
        val = tuple(float(x) for x in v.split(":")) if isinstance(cur, tuple) else type(cur)(float(v))
        if in_chain:
            backend_cfg = replace(backend_cfg, chain=replace(backend_cfg.chain, **{k: val}))
        else:
            backend_cfg = replace(backend_cfg, **{k: val})
    for world in args.worlds.split(","):
        run = simulate_run(world, None if args.route == "default" else args.route, seed=args.seed)
        backend = GraphBackEnd(backend_cfg, cfg.likelihood.sigma_hit)
        checks: list[tuple[float, np.ndarray, np.ndarray]] = []  # (stamp, newest node's pose, map-frame cov)
        add = backend.add

        def add_and_check(key, add=add, backend=backend, checks=checks):
            out = add(key)
            n = len(backend)
            if n % 10 == 0:
                p = backend.poses()[-1]  # read back: the graph's solution, nothing pending
                checks.append((key.stamp, p.copy(), backend.graph.newest_covariance()))
            return out

        backend.add = add_and_check
        traj, _ = run_estimator(run, cfg, backend=backend)
        graph_nees, graph_err, front_nees, front_err = [], [], [], []
        for stamp, pose, cov in checks:
            k = min(int(np.searchsorted(traj.stamps, stamp)), len(traj.stamps) - 1)
            truth = traj.truth[k]
            graph_nees.append(_nees(pose - truth, cov))
            graph_err.append(float(np.hypot(*(pose - truth)[:2])))
            front_nees.append(_nees(traj.poses[k] - truth, traj.covs[k]))
            front_err.append(float(np.hypot(*(traj.poses[k] - truth)[:2])))
        # the corrected estimate, as the runtime reports it (``corrected_estimate``, computed by run_estimator)
        front2_nees, front2_err, corr_nees, corr_err = [], [], [], []
        for k in [*range(0, len(traj.stamps), 40), len(traj.stamps) - 1]:
            truth = traj.truth[k]
            front2_nees.append(_nees(traj.poses[k] - truth, traj.covs[k]))
            front2_err.append(float(np.hypot(*(traj.poses[k] - truth)[:2])))
            corr_nees.append(_nees(traj.corrected[k] - truth, traj.corrected_covs[k]))
            corr_err.append(float(np.hypot(*(traj.corrected[k] - truth)[:2])))
        print(f"{run.world_name} seed {run.seed}: {len(backend.closures)} closures; "
              f"{_line('graph', graph_nees, graph_err)} | {_line('front end', front_nees, front_err)}\n"
              f"  every 40th scan: {_line('front end', front2_nees, front2_err)} | "
              f"{_line('corrected', corr_nees, corr_err)}", flush=True)
        if args.closures:
            nodes = np.minimum(np.searchsorted(traj.stamps, [k.stamp for k in backend.keys]), len(traj.stamps) - 1)
            truth = traj.truth[nodes]
            for c in backend.closures:
                e = relative(truth[c.anchor], truth[c.node]) - c.pose
                dxy, dyaw = c.error(truth[c.anchor], truth[c.node])
                kind = "all three" if np.allclose(c.proj, np.eye(3)) else "partial"
                print(f"  closure {c.anchor} -> {c.node} ({kind}): error {100 * np.hypot(e[0], e[1]):.2f} cm, "
                      f"{np.degrees(float(wrap_angle(e[2]))):+.3f} deg; in the directions it constrains "
                      f"{100 * dxy:.2f} cm, {np.degrees(dyaw):.3f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
