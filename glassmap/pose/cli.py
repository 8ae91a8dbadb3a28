"""``glassmap pose``: evaluate the pose + covariance estimator on simulated runs, benchmark it, and run the
paper's experiment online (glass maps from the estimator's poses).

Heavy imports (numpy, the simulator, torch) happen inside the handlers so ``glassmap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from glassmap.cli_args import (add_loop_closure, add_no_progress, add_out, add_seed, add_seeds, add_workers, add_world,
                                add_worlds)

DEFAULT_WORLDS = ["office", "room", "glass-corridor", "lobby"]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pose", help="pose estimator: trajectory error and covariance consistency, benchmark, online experiment",
        description="The online pose + covariance estimator (wheel odometry prediction, correlative scan-to-map "
        "matching with a covariance from the score distribution, EKF fusion). Evaluate it on simulated runs, "
        "time it, and run the paper's glass-map experiment with its poses.")
    sub = p.add_subparsers(dest="pose_command", required=True, metavar="POSE_COMMAND")

    e = sub.add_parser("eval", help="ATE, final drift and NEES on simulated runs through several worlds",
                       description="Simulate runs (one per world and seed), run the estimator causally (each scan "
                       "sees only the odometry received before it) and report per run: absolute trajectory error "
                       "(RMSE, max) and final drift of the base position against the truth, the same for raw "
                       "wheel odometry, the yaw RMSE, and covariance consistency: mean NEES (3 dof; ideal 3) and "
                       "the share of scans inside the 95 % bound. Writes a CSV and a JSON summary.")
    add_worlds(e, ",".join(DEFAULT_WORLDS))
    add_seeds(e, "0")
    e.add_argument("--route", default="default",
                   help="route name; 'default' = each world's default route (default: %(default)s)")
    e.add_argument("--glass-weighting", choices=["off", "online", "oracle"], default="off",
                   help="glass-aware matching as the runtime runs it (beams seen through believed glass "
                   "down-weighted: what lies behind a pane, and mirror ghosts of panes the map holds as glass): "
                   "'online' builds the glass map as the runtime does (classifier + glass mapper at the "
                   "estimated poses), 'oracle' writes the true glass cells into the grid's glass layer first "
                   "(the best case); default off")
    e.add_argument("--every-scan", action="store_true",
                   help="match and integrate every scan (no motion filter, EstimatorConfig.keyframe_*); default: "
                   "key scans only")
    e.add_argument("--sweep-motion", action="store_true",
                   help="simulate the robot's motion during each laser sweep (~19 ms; every beam from where the "
                   "laser is when it fires); default: all beams of a scan from one pose")
    e.add_argument("--deskew", action="store_true",
                   help="the estimator undoes the motion during the sweep with the odometry (EstimatorConfig."
                   "deskew); meaningful with --sweep-motion")
    e.add_argument("--odometry-lag", type=float, default=0.0, metavar="S",
                   help="odometry reaches the estimator S seconds after its stamp, as under CPU load (default 0)")
    e.add_argument("--drop-scans", type=float, default=0.0, metavar="SHARE",
                   help="this share (0-1) of the scans, drawn at random, never reaches the estimator (default 0)")
    e.add_argument("--no-return-range", type=float, default=None,
                   help="how far (m) a no-return beam (+inf) clears free space in the estimator's grid "
                   "(default: OccupancyParams' default)")
    add_loop_closure(e, default=False)
    add_out(e, "out/pose", "output directory for pose_eval.csv / .json")
    add_workers(e, "parallel processes, one run each (the per-scan times in the table are then measured on a "
                "shared machine)")
    add_no_progress(e)
    e.set_defaults(func=_eval)

    b = sub.add_parser("bench", help="time per scan of prediction + matching + covariance (median, one core)",
                       description="Run the estimator on a simulated run with torch and numpy limited to one "
                       "thread and report per-scan times: the hot path (odometry prediction + scan matching + "
                       "covariance + fusion; target <= 10 ms median), the likelihood-field rebuild (every few "
                       "scans, amortised) and the occupancy-grid update, each median / p90 / mean in ms.")
    add_world(b)
    b.add_argument("--route", default="short", help="route (default: short)")
    add_seed(b)
    b.add_argument("--scans", type=int, default=600, help="scans to time (default: 600)")
    b.set_defaults(func=_bench)

    x = sub.add_parser("experiment", help="the paper's experiment online: glass maps from the estimator's poses",
                       description="For each seed: simulate a run, estimate poses + covariances online, build "
                       "glass maps with each registration method from the estimator's laser poses and per-beam "
                       "registration sigma (sqrt(sigma_xy^2 + (r sigma_theta)^2 + sigma_r^2)), and score them "
                       "against the blueprint (classification error, as in `glassmap glass experiment`). With "
                       "--loop-closure, also the maps rebuilt from the key scans at the front end's poses "
                       "(<method>@keys) and at the pose graph's optimised poses (<method>@keys+lc). Writes a CSV, a "
                       "summary with robust3's margins over direct, and a box plot.")
    add_world(x)
    x.add_argument("--route", default="short", help="route (default: short; 'main' is 4x longer)")
    add_seeds(x, "0-9")
    x.add_argument("--methods", default="direct,robust3,robust5",
                   help="registration methods (default: direct,robust3,robust5)")
    x.add_argument("--glass-scans", choices=("keys", "every"), default="keys",
                   help="which scans the online maps register: keys (default: each key scan as the estimator matches "
                   "it, as the runtime does) or every (every --glass-every-th scan)")
    x.add_argument("--glass-every", type=int, default=4,
                   help="with --glass-scans every: map glass on every k-th scan (default: 4 = 10 Hz)")
    x.add_argument("--compare-glass-scans", action="store_true",
                   help="also build online maps <method>@<other>-online registered on the other kind of scans, on "
                   "the same trials")
    x.add_argument("--sigma", default="map",
                   help="where the registration sigma comes from: map (the pose's covariance relative to the map "
                   "built so far, the default) or anchor (the reported covariance, relative to the map frame's "
                   "anchor); a list (map,anchor) also builds online maps <method>~<source> of the robust methods "
                   "with the others, on the same trials")
    add_loop_closure(x, default=False)
    add_out(x, "out/pose")
    x.set_defaults(func=_experiment)

    g = sub.add_parser("margins", help="the robust methods' margins over direct per world and over worlds, from "
                       "experiment CSVs",
                       description="Read the CSVs of `glassmap pose experiment` (one or more worlds) and print, per "
                       "world and kind of map, each robust method's (robust3, robust3-vis, robust3~<sigma>, ...) "
                       "gain over direct in mean, worst "
                       "and std of the error over trials, trial by trial (trials where robust3's error is lower, "
                       "and the mean paired difference direct - robust3 in points of error with its standard "
                       "error), then over the worlds the mean gain and the worst world's.")
    g.add_argument("csv", nargs="+", help="experiment CSV files")
    g.set_defaults(func=_margins)



def _eval(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from tqdm import tqdm

    from glassmap.pose.estimator import EstimatorConfig

    worlds = [w.strip() for w in args.worlds.split(",") if w.strip()]
    seeds = args.seeds
    oracle = args.glass_weighting == "oracle"
    online = args.glass_weighting == "online"
    cfg = replace(EstimatorConfig(), glass_weighting=oracle or online)
    if args.every_scan:
        cfg = replace(cfg, keyframe_distance=0.0, keyframe_angle=0.0)
    if args.deskew:
        cfg = replace(cfg, deskew=True)
    if args.no_return_range is not None:
        if args.no_return_range < 0:
            raise SystemExit(f"--no-return-range must be >= 0 m, got {args.no_return_range}")
        cfg = replace(cfg, occupancy=replace(cfg.occupancy, no_return_range=args.no_return_range))
    if args.odometry_lag < 0 or not 0 <= args.drop_scans < 1:
        raise SystemExit(f"--odometry-lag must be >= 0 s and --drop-scans in [0, 1), got {args.odometry_lag}, "
                         f"{args.drop_scans}")
    route = None if args.route == "default" else args.route
    _check_worlds(worlds, route)
    backend = None
    if args.loop_closure:
        from glassmap.pose.backend import BackEndConfig

        backend = BackEndConfig()
    options = dict(glass_oracle=oracle, sweep_motion=args.sweep_motion, glass_online=online,
                   backend_config=backend, odometry_lag=args.odometry_lag, drop_scans=args.drop_scans)
    jobs = [(w, route, s, cfg, options) for w in worlds for s in seeds]
    rows: list[dict | None] = [None] * len(jobs)
    bar = tqdm(total=len(jobs), desc="pose eval", unit="run", disable=args.no_progress)
    workers = min(args.workers or os.cpu_count() or 1, len(jobs))
    if workers <= 1:
        for i, job in enumerate(jobs):
            rows[i] = _eval_job(job)
            tqdm.write(_line(rows[i]))
            bar.update(1)
    else:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        from glassmap.threads import one_thread

        with ProcessPoolExecutor(max_workers=workers, initializer=one_thread) as pool:
            futures = {pool.submit(_eval_job, job): i for i, job in enumerate(jobs)}
            for f in as_completed(futures):
                rows[futures[f]] = f.result()
                tqdm.write(_line(rows[futures[f]]))
                bar.update(1)
    bar.close()
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, "pose_eval" + (f"_glass_{args.glass_weighting}" if oracle or online else "")
                        + ("_every_scan" if args.every_scan else "")
                        + ("_sweep" if args.sweep_motion else "") + ("_deskew" if args.deskew else "")
                        + (f"_noret{args.no_return_range:g}" if args.no_return_range is not None else "")
                        + ("_loop_closure" if args.loop_closure else "")
                        + (f"_lag{args.odometry_lag:g}" if args.odometry_lag else "")
                        + (f"_drop{args.drop_scans:g}" if args.drop_scans else ""))
    _write_csv(stem + ".csv", rows)
    with open(stem + ".json", "w") as f:
        json.dump(rows, f, indent=1)
    print(f"wrote {stem}.csv and {stem}.json")
    return 0


def _check_worlds(worlds: list[str], route: str | None) -> None:
    """Load every world and look its route up before the first run (a typo stops the command at once, not
    after hours of runs: WorldFileError, RouteError)."""
    from glassmap.sim.world import load_world

    if not worlds:
        raise SystemExit("error: --worlds names no world")
    for w in worlds:
        load_world(w).route(route)


_CLASSIFIER = None  # the shipped classifier, loaded once per process for --glass-weighting online


def _eval_job(job: tuple) -> dict:
    """One run of ``glassmap pose eval`` (world, route, seed, EstimatorConfig, evaluate_run options) -> its
    metrics as a dict; runs in a worker process with --workers."""
    global _CLASSIFIER
    from glassmap.pose.evaluate import evaluate_run

    world, route, seed, cfg, options = job
    if options["glass_online"] and _CLASSIFIER is None:
        from glassmap.classifier import GlassClassifier

        _CLASSIFIER = GlassClassifier.load_default()
    m = evaluate_run(world, route, seed, cfg, classifier=_CLASSIFIER, **options)
    return m.as_dict()


def _line(r: dict) -> str:
    lc = ""
    if r.get("lc_ate_rmse") == r.get("lc_ate_rmse"):  # a back end ran (not NaN)
        lc = (f"\n    with loop closure: ATE {100 * r['lc_ate_rmse']:5.1f} cm online (max {100 * r['lc_ate_max']:5.1f}), "
              f"{100 * r['lc_opt_ate_rmse']:5.1f} cm optimised (max {100 * r['lc_opt_ate_max']:5.1f}), final drift "
              f"{100 * r['lc_final_drift']:5.1f} cm, mean NEES {r['lc_nees_mean']:.2f} ({100 * r['lc_inside_95']:.0f} % inside "
              f"the 95 % bound) | closures {r['lc_closures']} ({r['lc_false_closures']} false) "
              f"of {r['lc_checks']} checks, {r['lc_chain_unscaled']} unscaled the chain | back end "
              f"{r['lc_backend_ms_mean']:.1f} ms mean per key scan "
              f"(max {r['lc_backend_ms_max']:.0f})")
    return (f"{r['world']:15s} seed {r['seed']:3d}  ATE {100 * r['ate_rmse']:5.1f} cm (max {100 * r['ate_max']:5.1f}) "
            f"drift {100 * r['final_drift']:5.1f} cm | odometry ATE {100 * r['odom_ate_rmse']:6.1f} cm drift "
            f"{100 * r['odom_final_drift']:6.1f} cm | yaw {r['yaw_rmse_deg']:.2f} deg | NEES {r['nees_mean']:5.2f} "
            f"in95 {100 * r['inside_95']:5.1f} % (key scans {r['nees_key_mean']:.2f}, between "
            f"{r['nees_between_mean']:.2f}; yaw alone {r['yaw_nees_key_mean']:.2f}, {r['yaw_nees_between_mean']:.2f}; "
            f"each axis alone: along {r['along_nees_mean']:.2f}, across {r['cross_nees_mean']:.2f}, yaw "
            f"{r['yaw_nees_mean']:.2f}) "
            f"| gated {r['gated']} lost {r['lost_events']} ambiguous "
            f"{r['ambiguous_events']} | sigma_xy {100 * r['sigma_xy_mean']:.1f} cm | "
            f"key scans {100 * r['key_share']:.0f} % | core {r['t_core_median_ms']:.2f} ms (key scans "
            f"{r['t_core_key_median_ms']:.2f} ms)" + lc)


def _write_csv(path: str, rows: list[dict]) -> None:
    import csv

    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _bench(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np
    import torch

    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from glassmap.pose.evaluate import run_estimator
    from glassmap.sim.dataset import simulate_run

    print(f"simulating {args.world}/{args.route} seed {args.seed} ...", file=sys.stderr)
    run = simulate_run(args.world, args.route, seed=args.seed)
    n = min(args.scans, run.n_scans)
    run = dataclasses.replace(run, scan_stamps=run.scan_stamps[:n], ranges=run.ranges[:n],
                              intensities=run.intensities[:n], scan_true_poses=run.scan_true_poses[:n],
                              laser_poses=run.laser_poses[:n])
    traj, est = run_estimator(run)
    skip = 10  # the first scans build the map
    keys = traj.key[skip:]
    rows = [("prediction + matching + covariance + fusion", 1e3 * traj.t_core[skip:])]
    if keys.any():  # the key scans' share of that: the matched ones
        rows.append((f"  ... on key scans only ({100 * keys.mean():.0f} % of scans)", 1e3 * traj.t_core[skip:][keys]))
    rows += [("likelihood field, rebuild or update (per scan, amortised)", 1e3 * traj.t_field[skip:]),
             ("occupancy-grid update", 1e3 * traj.t_integrate[skip:])]
    for name, ms in rows:
        print(f"{name:48s} median {np.median(ms):6.2f} ms  p90 {np.percentile(ms, 90):6.2f} ms  "
              f"mean {ms.mean():6.2f} ms")
    rebuilds = traj.t_field[skip:][traj.t_field[skip:] > 0] * 1e3
    if rebuilds.size:
        how = (f"updated at every key scan, rebuilt {est.stats.field_rebuilds} times" if est.config.field_incremental
               else f"rebuilt every {est.config.field_refresh_scans} key scans")
        print(f"{'likelihood field (when brought up to date)':48s} median {np.median(rebuilds):6.2f} ms  "
              f"p90 {np.percentile(rebuilds, 90):6.2f} ms  {how}")
    print(f"scans {n - skip}, matched {traj.matched}, no match {traj.no_match}, gated {traj.gated}; "
          f"numpy/torch threads: 1 (OMP_NUM_THREADS must be set before start for numpy's BLAS)")
    return 0


def _experiment(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from glassmap.classifier import GlassClassifier
    from glassmap.eval.experiment import box_plot, format_summary, summarise, write_csv
    from glassmap.pose.experiment import OnlineTrialConfig, run_online_trial

    seeds = args.seeds
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    sigmas = tuple(m.strip() for m in args.sigma.split(",") if m.strip())
    cfg = OnlineTrialConfig(world=args.world, route=args.route, methods=methods, glass_every=args.glass_every,
                            glass_scans=args.glass_scans, compare_glass_scans=args.compare_glass_scans,
                            sigmas=sigmas, loop_closure=args.loop_closure)
    clf = GlassClassifier.load_default()
    rows = []
    for s in tqdm(seeds, desc="online trials", unit="trial"):
        rows.extend(run_online_trial(cfg, s, classifier=clf))
    os.makedirs(args.out, exist_ok=True)
    world = os.path.splitext(os.path.basename(args.world))[0]
    stem = os.path.join(args.out, f"online_{world}_{args.route}" + ("_loop_closure" if args.loop_closure else ""))
    write_csv(stem + ".csv", rows)
    title = (f"online: {args.world}/{args.route}, {len(seeds)} trials, poses + sigma from the pose estimator")
    box_plot(stem + ".png", rows, title)
    summary = summarise(rows)
    text = format_summary(summary, title)
    ate = [r["ate_rmse"] for r in rows if r["method"] == methods[0]]
    nees = [r["nees_mean"] for r in rows if r["method"] == methods[0]]
    sig = [r["sigma_median"] for r in rows if r["method"] == methods[0]]
    import numpy as np

    text += (f"\npose: ATE RMSE mean {100 * np.mean(ate):.1f} cm (worst {100 * np.max(ate):.1f}), mean NEES "
             f"{np.mean(nees):.2f}, median registration sigma {100 * np.median(sig):.1f} cm")
    from glassmap.pose.experiment import margins

    compared = [margins(summary, methods[0], m) for m in methods[1:] if m.startswith("robust")]
    compared += [margins(summary, methods[0], f"robust3~{src}", ("",)) for src in sigmas[1:]]
    for m in [m for ms in compared for m in ms] if not methods[0].startswith("robust") else []:
        text += (f"\n{m['other']} vs {m['base']} ({m['maps']} maps): gain in mean {100 * m['mean_gain']:+.1f} %, worst "
                 f"{100 * m['worst_gain']:+.1f} %, std {100 * m['std_gain']:+.1f} % -> "
                 f"{'beats it in all three' if m['beats'] else 'does not beat it in all three'}")
    if args.loop_closure:
        first = [r for r in rows if r["method"] == methods[0]]
        text += (f"\nkey scans: ATE RMSE at the front end's poses mean {100 * np.mean([r['keys_ate'] for r in first]):.1f}"
                 f" cm (worst {100 * np.max([r['keys_ate'] for r in first]):.1f}), at the optimised poses mean "
                 f"{100 * np.mean([r['keys_lc_ate'] for r in first]):.1f} cm (worst "
                 f"{100 * np.max([r['keys_lc_ate'] for r in first]):.1f}); loop closures per trial "
                 f"{[r['closures'] for r in first]}, of them false {[r['false_closures'] for r in first]}")
    with open(stem + ".txt", "w") as f:
        f.write(text + "\n")
    print(text)
    print(f"wrote {stem}.csv, {stem}.png, {stem}.txt")
    return 0


def _margins(args: argparse.Namespace) -> int:
    import csv

    from glassmap.pose.experiment import world_margins

    rows = []
    for path in args.csv:
        with open(path, newline="") as f:
            rows.extend(csv.DictReader(f))
    others = sorted({r["method"] for r in rows if r["method"].startswith("robust") and "@" not in r["method"]})
    per_world, overall = world_margins(rows, others=tuple(others))
    print(f"{'world':28s} {'method':15s} {'maps':8s} {'mean':>7s} {'worst':>7s} {'std':>7s}  beats  "
          f"{'trials won':>10s}  {'paired diff +- se (points)':>26s}")
    for m in per_world:
        print(f"{os.path.splitext(os.path.basename(m['world']))[0]:28s} {m['other']:15s} {m['maps']:8s} "
              f"{100 * m['mean_gain']:+6.1f}% {100 * m['worst_gain']:+6.1f}% {100 * m['std_gain']:+6.1f}%  "
              f"{'yes' if m['beats'] else 'no ':5s}  {m['wins']:4d} of {m['n']:<3d}  "
              f"{100 * m['diff']:+19.2f} +- {100 * m['diff_se']:.2f}")
    print("over the worlds: mean gain (worst world's gain, that world)")
    for o in overall:
        parts = [f"{k} {100 * o[f'{k}_gain']:+.1f} % ({100 * o[f'{k}_gain_worst']:+.1f} %, "
                 f"{os.path.splitext(os.path.basename(o[f'{k}_gain_worst_world']))[0]})" for k in ("mean", "worst", "std")]
        print(f"{o['other']} vs direct, {o['maps']} maps, {o['worlds']} worlds: " + "; ".join(parts)
              + f"; beats direct in all three on {o['beats']} of {o['worlds']}; lower error in {o['wins']} of "
              f"{o['trials']} trials")
    return 0
