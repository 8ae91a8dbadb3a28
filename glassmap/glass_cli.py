"""``glassmap glass``: the glass-map core: ``train``, ``eval``, ``angles``, ``map``, ``experiment``, ``bench``
(``label`` reads recordings and is added by runtime/cli.py)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

from glassmap import classifier_cli
from glassmap.cli_args import add_out, add_seed, add_workers, add_world, add_worlds


def register(subparsers: argparse._SubParsersAction) -> argparse._SubParsersAction:
    g = subparsers.add_parser(
        "glass", help="glass classifier and glass maps: train, eval, label, angles, map, experiment, bench",
        description="The glass path: incidence angles, the p(glass) classifier, registration onto the grid and "
        "the Bayesian glass map. Train the classifier, compare incidence-angle methods, map a simulated run, "
        "run the paper's experiment (direct vs robust registration) and time the per-scan path.")
    sub = g.add_subparsers(dest="glass_command", required=True, metavar="GLASS_COMMAND")

    p = sub.add_parser("train", help="train the glass classifiers (context, baseline) on generated worlds or "
                       "on labelled recordings",
                       description="Simulate labelled beams from generated training worlds (each with its own "
                       "laser and material parameters), train the 4-layer MLP of each model (class-balanced), with "
                       "early stopping and temperature scaling on generated validation worlds; or train / fine-tune "
                       "on labelled recordings (`glassmap glass label`). Writes <out>/glass_<model>.npz/.pt/.json; the "
                       "shipped weights change only with --replace-shipped. Test-world seeds (0-99) are refused.")
    classifier_cli.add_train_arguments(p)
    p.set_defaults(func=classifier_cli.cmd_train)

    p = sub.add_parser("eval", help="score glass classifiers without retraining: test worlds or a labelled recording",
                       description="Score classifiers on the benchmark's test worlds (generated test seeds and the "
                       "built-in worlds; the same labelled beams as `glassmap eval`'s classifier part), on world "
                       "files, or on a labelled recording; per world, mean and worst world. Writes <out>/eval.json.")
    classifier_cli.add_eval_arguments(p)
    p.set_defaults(func=classifier_cli.cmd_eval)

    p = sub.add_parser("experiment", help="the paper's experiment: direct vs robust registration over many trials",
                       description="Trials on a simulated world: the estimated pose is the true pose plus a "
                       "time-correlated error (sigma_xy, sigma_theta, tau); maps are built with every method on "
                       "the same data and scored against the blueprint. Writes a CSV and a box plot, prints "
                       "mean / worst / std per method; --sweep also runs sigma_xy = 0, 1, 2, 5, 10 cm.")
    add_world(p)
    p.add_argument("--route", default=None, help="route name (default: the world's default route)")
    p.add_argument("--trials", type=int, default=50, help="number of trials (default: %(default)s)")
    p.add_argument("--duration", type=float, default=None, help="drive at most this many seconds per trial")
    p.add_argument("--scan-rate", type=float, default=5.0, help="scans mapped per second (Hz, default: %(default)s)")
    p.add_argument("--sigma-xy", type=float, default=0.05,
                   help="position error std per axis (m, default: %(default)s)")
    p.add_argument("--sigma-theta", type=float, default=math.radians(0.25),
                   help="heading error std (rad, default: 0.25 deg)")
    p.add_argument("--tau", type=float, default=2.0, help="error correlation time (s, default: %(default)s)")
    p.add_argument("--sigma-mode", default="beam", choices=["beam", "xy"],
                   help="registration sigma per beam sqrt(sxy^2 + (r sth)^2) (default) or sigma_xy only")
    p.add_argument("--methods", default=None, help="comma separated (default: direct, robust3, robust5, "
                   "robust3-endpoint, direct-beam, robust3-beam); all: " + ", ".join([
                       "direct", "robust3", "robust5", "robust3-endpoint", "robust5-endpoint", "direct-beam",
                       "robust3-beam", "robust5-beam", "robust3-protect-glass", "robust3-no-protect",
                       "robust3-plain"]))
    p.add_argument("--max-free-range", type=float, default=10.0,
                   help="m a beam clears in the occupancy update (default: %(default)s; the grid default is 20)")
    p.add_argument("--map-poses", choices=["truth", "estimate"], default="truth",
                   help="poses the shared occupancy grid is built from: 'truth' (default; a consistent map, as "
                   "a SLAM back end gives, with only the robot's pose against it uncertain) or 'estimate' "
                   "(the registration's noisy poses, which also smear the walls of the occupancy grid)")
    p.add_argument("--sweep", action="store_true", help="also sweep sigma_xy over --sweep-sigmas")
    p.add_argument("--sweep-sigmas", default="0,0.01,0.02,0.05,0.10",
                   help="sigma_xy values (m) of the sweep (default: %(default)s)")
    p.add_argument("--sweep-trials", type=int, default=10, help="trials per sigma in the sweep (default: %(default)s)")
    add_workers(p)
    add_seed(p, 1000, "first trial seed")
    add_out(p, "out/experiment")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("angles", help="benchmark the incidence-angle extractors against the simulator's truth",
                       description="Simulate scans at poses along the routes of some worlds and compare the "
                       "Hough and split-and-merge incidence angles with the true angles: coverage, median / "
                       "p90 / p99 error, time per scan (one core).")
    add_worlds(p, "office,glass-corridor,lobby,room")
    p.add_argument("--scans", type=int, default=60, help="scans per world (default: %(default)s)")
    add_seed(p)
    p.set_defaults(func=cmd_angles)

    p = sub.add_parser("map", help="build the glass confidence map of a simulated run and export it",
                       description="Drive a world's route (or load a dataset from `glassmap sim run`), add the "
                       "pose error model, build the maps and write PNG (paper colours), .npy probabilities "
                       "and PGM + YAML.")
    add_world(p)
    p.add_argument("--dataset", default=None, help="a .npz from `glassmap sim run` (uses its true laser poses)")
    p.add_argument("--method", default="robust3", help="registration method (default: %(default)s)")
    p.add_argument("--sigma-xy", type=float, default=0.05, help="position error std per axis (m, default: %(default)s)")
    p.add_argument("--sigma-theta", type=float, default=math.radians(0.25),
                   help="heading error std (rad, default: 0.25 deg)")
    p.add_argument("--tau", type=float, default=2.0, help="error correlation time (s, default: %(default)s)")
    p.add_argument("--scan-rate", type=float, default=10.0, help="scans used per second (Hz, default: %(default)s)")
    p.add_argument("--duration", type=float, default=None, help="drive at most this many seconds")
    add_seed(p)
    add_out(p, "out/map")
    p.add_argument("--stem", default="glass_map", help="file name stem of the exported maps (default: %(default)s)")
    p.add_argument("--map-poses", choices=["truth", "estimate"], default="truth",
                   help="poses the occupancy grid is built from (see `glassmap glass experiment --help`; "
                   "default: truth)")
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("bench", help="time of the per-scan glass path on one core",
                       description="Per-scan time of incidence angles + classifier + registration + update on "
                       "1081-beam office scans (numpy's BLAS on one thread), after building a map; the "
                       "occupancy update is timed separately.")
    p.add_argument("--scans", type=int, default=200, help="scans to time (default: %(default)s)")
    p.add_argument("--method", default="robust3", help="registration method (default: %(default)s)")
    p.add_argument("--angle-method", default="split-merge", choices=["split-merge", "hough"],
                   help="incidence-angle method (default: %(default)s)")
    p.add_argument("--link-lag", type=int, default=None,
                   help="split-merge second pass look-back (AngleParams.link_lag; 0 = no second pass)")
    p.add_argument("--model", default="context", choices=["context", "baseline"],
                   help="shipped glass classifier (default: %(default)s)")
    p.set_defaults(func=cmd_bench)
    return sub  # runtime/cli.py adds `label` (it reads recordings, which the core cannot)


def _single_thread() -> None:
    """numpy's BLAS (the classifier's network) and torch (training) on one thread: their products are small."""
    from .threads import one_thread

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    one_thread()


def cmd_experiment(args) -> int:
    from .eval.experiment import box_plot, format_summary, rows_of, run_trials, summarise, sweep, sweep_plot, write_csv
    from .eval.pose_error import PoseErrorModel
    from .eval.trial import DEFAULT_METHODS, TrialConfig

    if args.trials < 1:
        print("--trials must be >= 1", file=sys.stderr)
        return 2
    methods = tuple(m for m in args.methods.split(",") if m) if args.methods else DEFAULT_METHODS
    try:
        cfg = TrialConfig(world=args.world, route=args.route, duration=args.duration, scan_rate=args.scan_rate,
                          pose_error=PoseErrorModel(args.sigma_xy, args.sigma_theta, args.tau),
                          sigma_mode=args.sigma_mode, methods=methods, max_free_range=args.max_free_range,
                          map_poses=args.map_poses)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    seeds = list(range(args.seed, args.seed + args.trials))
    t0 = time.perf_counter()
    rows = rows_of(run_trials(cfg, seeds, args.workers or None))
    csv_path = write_csv(os.path.join(args.out, "trials.csv"), rows)
    title = (f"{args.world}, {args.trials} trials, sigma_xy {args.sigma_xy * 100:.0f} cm, "
             f"sigma_theta {math.degrees(args.sigma_theta):.2f} deg, map from {args.map_poses} poses")
    png = box_plot(os.path.join(args.out, "boxplot.png"), rows, title)
    summary = summarise(rows)
    print(format_summary(summary, title))
    result = {"config": title, "summary": summary}
    if args.sweep:
        sig = [float(s) for s in args.sweep_sigmas.split(",") if s]
        sseeds = list(range(args.seed, args.seed + args.sweep_trials))
        srows = sweep(cfg, sig, sseeds, args.workers or None)
        write_csv(os.path.join(args.out, "sweep.csv"), srows)
        sweep_plot(os.path.join(args.out, "sweep.png"), srows)
        result["sweep"] = {}
        for s in sig:
            sm = summarise([r for r in srows if r["sigma_xy"] == s])
            result["sweep"][str(s)] = sm
            print(format_summary(sm, f"sweep: sigma_xy {s * 100:.0f} cm ({args.sweep_trials} trials)"))
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(result, f, indent=2)
    print(f"wrote {csv_path}, {png}, summary.json in {time.perf_counter() - t0:.0f} s")
    return 0


def cmd_angles(args) -> int:
    import numpy as np

    from .angles import METHODS, incidence_angles
    from .sim.laser import simulate_scan
    from .sim.world import load_world
    from .train import sample_poses

    _single_thread()
    rng = np.random.default_rng(args.seed)
    sims = []
    for name in (w for w in args.worlds.split(",") if w):
        world = load_world(name)
        for pose in sample_poses(world, args.scans, rng):
            sims.append(simulate_scan(world, pose, rng))
    print(f"{len(sims)} scans; error against the simulator's true incidence angle on returned beams")
    print(f"{'method':12s} {'coverage':>8s} {'median':>8s} {'p90':>8s} {'p99':>8s} {'ms/scan':>8s} {'glass cov':>9s} "
          f"{'glass p90':>9s}")
    for m in METHODS:
        errs, cov, gcov, times, gerr = [], [], [], [], []
        for s in sims:
            t0 = time.perf_counter()
            inc = incidence_angles(s.geometry.angles, s.ranges, m).incidence
            times.append(time.perf_counter() - t0)
            ret = np.isfinite(s.ranges) & np.isfinite(s.incidence)
            ok = ret & np.isfinite(inc)
            errs.append(np.degrees(np.abs(inc[ok] - s.incidence[ok])))
            cov.append((ok.sum(), ret.sum()))
            g = ret & s.is_glass
            gcov.append(((g & ok).sum(), g.sum()))
            gerr.append(np.degrees(np.abs(inc[g & ok] - s.incidence[g & ok])))
        e = np.concatenate(errs)
        c = sum(a for a, _ in cov) / max(sum(b for _, b in cov), 1)
        gc = sum(a for a, _ in gcov) / max(sum(b for _, b in gcov), 1)
        ge = np.concatenate(gerr)
        g90 = np.percentile(ge, 90) if ge.size else float("nan")
        print(f"{m:12s} {c:8.3f} {np.median(e):8.3f} {np.percentile(e, 90):8.3f} {np.percentile(e, 99):8.3f} "
              f"{np.median(times) * 1e3:8.2f} {gc:9.3f} {g90:9.3f}")
    print("errors in degrees; coverage = share of returned beams with an angle; glass cov = the same for "
          "returns from glass")
    return 0


def cmd_map(args) -> int:
    import numpy as np

    from .eval.pose_error import PoseErrorModel
    from .eval.trial import METHODS, TrialConfig, build_maps_for_export
    from .mapping import GlassMapper, MapperConfig

    if args.method not in METHODS:
        print(f"error: unknown method {args.method!r}; known: {', '.join(METHODS)}", file=sys.stderr)
        return 2
    _single_thread()  # a 1081 x 32 matmul gains nothing from threads, and loses a lot on a busy machine
    pe = PoseErrorModel(args.sigma_xy, args.sigma_theta, args.tau)
    if args.dataset:
        from tqdm import tqdm

        from .sim.dataset import SimRun

        run = SimRun.load(args.dataset)
        every = max(1, int(round(run.n_scans / max(run.duration, 1e-9) / args.scan_rate)))
        idx = np.arange(0, run.n_scans, every)
        est = run.laser_poses[idx] + pe.sample(run.scan_stamps[idx], np.random.default_rng(args.seed))
        mapper = GlassMapper(None, MapperConfig(**METHODS[args.method]))
        for j, i in enumerate(tqdm(idx, desc="mapping", unit="scan")):
            scan = run.scan(int(i))
            occ_pose = run.laser_poses[i] if args.map_poses == "truth" else est[j]
            mapper.process(scan, est[j], pe.beam_sigma(scan.ranges), occupancy_pose=occ_pose)
    else:
        cfg = TrialConfig(world=args.world, scan_rate=args.scan_rate, pose_error=pe, duration=args.duration,
                          map_poses=args.map_poses)
        mapper = build_maps_for_export(cfg, args.seed, args.method)
    paths = mapper.export(args.out, args.stem)
    for k, v in paths.items():
        print(f"{k:5s} {v}")
    return 0


def cmd_bench(args) -> int:
    import numpy as np

    from .angles import incidence_angles
    from .eval.trial import METHODS
    from .mapping import GlassMapper, MapperConfig
    from .sim.laser import simulate_scan
    from .sim.world import load_world
    from .train import sample_poses

    _single_thread()
    world = load_world("office")
    rng = np.random.default_rng(0)
    poses = sample_poses(world, args.scans, rng)
    sims = [simulate_scan(world, p, rng) for p in poses]
    scans = [s.to_scan(stamp=0.025 * i, seq=i) for i, s in enumerate(sims)]
    from dataclasses import replace

    from .angles import AngleParams

    ap = AngleParams() if args.link_lag is None else replace(AngleParams(), link_lag=args.link_lag)
    from .classifier import GlassClassifier

    clf = GlassClassifier.load_default(args.model)
    mapper = GlassMapper(None, MapperConfig(angle_method=args.angle_method, angle_params=ap, **METHODS[args.method]),
                         classifier=clf)
    t_occ = []
    for p, sc in zip(poses, scans):  # build the map first (occupancy timed separately)
        t0 = time.perf_counter()
        mapper.integrate(sc, p)
        t_occ.append(time.perf_counter() - t0)
    stages = {"angles": [], "classifier (features + MLP)": [], "classify (angles + classifier)": [],
              "registration + update": [], "total": []}
    cpu_clf: list[float] = []  # CPU time of this thread: what the classifier costs when the machine is shared
    for p, sc in zip(poses, scans):
        t0 = time.perf_counter()
        inc = incidence_angles(sc.angles, sc.ranges, args.angle_method, ap)
        t1 = time.perf_counter()
        use = np.isfinite(inc.incidence) & np.isfinite(sc.ranges) & np.isfinite(sc.intensities)
        tc, cc = time.perf_counter(), time.thread_time()
        clf.predict_scan(sc, inc, use)
        stages["classifier (features + MLP)"].append(time.perf_counter() - tc)
        cpu_clf.append(time.thread_time() - cc)
        t1b = time.perf_counter()
        beams, use = mapper.classify(sc)
        t2 = time.perf_counter()
        mapper.mark_glass_hits(beams, use, sc, p)
        mapper.register(beams, use, sc, p, np.full(len(sc.ranges), 0.05))
        t3 = time.perf_counter()
        mapper.process(sc, p, 0.05, update_occupancy=False)
        t4 = time.perf_counter()
        stages["angles"].append(t1 - t0)
        stages["classify (angles + classifier)"].append(t2 - t1b)
        stages["registration + update"].append(t3 - t2)
        stages["total"].append(t4 - t3)
    print(f"glass path per 1081-beam office scan, one core, {args.method}, {args.angle_method}, {args.model} "
          f"classifier ({len(scans)} scans): median / p90 ms")
    for k, v in stages.items():
        v = np.array(v) * 1e3
        print(f"  {k:28s} {np.median(v):6.2f} / {np.percentile(v, 90):6.2f}")
    v = np.array(cpu_clf) * 1e3
    print(f"  {'classifier, CPU time':28s} {np.median(v):6.2f} / {np.percentile(v, 90):6.2f}  (thread CPU time: "
          "unaffected by other processes waiting for the core)")
    v = np.array(t_occ) * 1e3
    print(f"  {'occupancy integrate (grid)':28s} {np.median(v):6.2f} / {np.percentile(v, 90):6.2f}  (not part of the "
          "glass path; done by the pose estimator at run time)")
    print("targets: total <= 3 ms; classifier (features + MLP) <= 0.5 ms")
    return 0
