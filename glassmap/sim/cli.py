"""``glassmap sim``: list worlds, drive a route and write a dataset, render PNGs, benchmark the laser model.

Heavy imports (numpy, the simulator, matplotlib) happen inside the handlers so ``glassmap --help`` is fast.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from glassmap.cli_args import add_no_progress, add_out, add_seed, add_world, seed_number


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim", help="simulator: drive a route through a world, render worlds and scans, benchmark",
        description="The simulator: a 2D world of segments with materials (glass, walls, frames, metal, "
        "whiteboards, retroreflective tape, dark furniture), a Hokuyo UTM-30LX-EW laser model with glass "
        "physics and a Pioneer 3-DX with noisy wheel odometry. Built-in worlds: office, glass-corridor, room, "
        "lobby (or give a path to a .toml world file; format in docs/simulator.md).")
    sub = p.add_subparsers(dest="sim_command", required=True, metavar="SIM_COMMAND")

    w = sub.add_parser("worlds", help="list the built-in worlds with their routes",
                       description="List the built-in worlds: segments per material, routes with their "
                       "length and clearance from the walls.")
    w.set_defaults(func=_worlds)

    g = sub.add_parser("generate", help="write a generated world (.toml), deterministic per seed",
                       description="Generate a random building (office, corridor, lobby or atrium; walls at any "
                       "angle, glass facades, partitions and doors, distractors, clutter, per-world laser and "
                       "material parameters, a checked loop route) in the TOML world format. Seeds 0-99 are "
                       "test worlds (glassmap eval), 1000-1999 validation, 10000-99999 training.")
    g.add_argument("--seed", type=seed_number, required=True, help="world seed (an integer >= 0)")
    g.add_argument("--kind", choices=("office", "corridor", "lobby", "atrium"), default=None,
                   help="kind of building (default: by the seed, seed %% 4)")
    g.add_argument("--out", default=None, help="output .toml (default: out/worlds/gen-<kind>-<seed>.toml)")
    g.add_argument("--render", default=None, metavar="PNG", help="also render the world to this PNG")
    g.set_defaults(func=_generate)

    r = sub.add_parser("run", help="drive a route through a world and write the dataset (.npz)",
                       description="Drive the robot along a route of a world and write scans (ranges, "
                       "intensities, 40 Hz), odometry (10 Hz), true poses and per-beam labels (material, true "
                       "range, incidence angle, glass) to an .npz file (glassmap.sim.dataset.SimRun). The same "
                       "--seed gives the same file contents.")
    add_world(r)
    r.add_argument("--route", default=None, help="route name in the world (default: the world's default route)")
    add_seed(r, what="random seed for odometry and laser noise")
    add_out(r, None, "output .npz (None: out/sim/<world>-<route>-s<seed>.npz)")
    r.add_argument("--max-v", type=float, default=0.5, help="largest forward speed, m/s (default: 0.5)")
    r.add_argument("--max-omega-deg", type=float, default=60.0, help="largest turn rate, deg/s (default: 60)")
    r.add_argument("--no-multi-echo", action="store_true", help="do not record the last echo")
    r.add_argument("--perfect-odometry", action="store_true", help="odometry without systematic or random error")
    r.add_argument("--uncompressed", action="store_true", help="write an uncompressed .npz (faster, larger)")
    add_no_progress(r)
    r.set_defaults(func=_run)

    d = sub.add_parser("render", help="PNG of a world, of its blueprint, or of a scan at a pose",
                       description="Render a PNG: 'world' (segments coloured by material, routes, start pose), "
                       "'blueprint' (ground truth grid: free white, wall dark, glass red; north up) or 'scan' "
                       "(a simulated scan at --pose, end points coloured by material or intensity).")
    d.add_argument("what", choices=["world", "blueprint", "scan"], help="what to render")
    add_world(d)
    add_out(d, None, "output PNG (None: out/sim/<world>-<what>.png)")
    d.add_argument("--resolution", type=float, default=0.05, help="blueprint cell size, m (default: 0.05)")
    d.add_argument("--pose", default=None, help="laser pose 'x,y,yaw_deg' in the map frame for 'scan' "
                   "(default: the world's start pose with the laser mount offset)")
    d.add_argument("--color-by", choices=["material", "intensity"], default="material",
                   help="scan end-point colours (default: material)")
    add_seed(d, what="random seed of the scan")
    d.set_defaults(func=_render)

    b = sub.add_parser("bench", help="time to simulate one scan (median / p90 ms, one core)",
                       description="Time simulate_scan for one 1081-beam scan at poses along the world's "
                       "default route, pinned to one CPU core with numpy/BLAS/torch limited to one thread. "
                       "Target: at most 2 ms per scan of 'office'.")
    add_world(b)
    b.add_argument("-n", type=int, default=400, help="number of timed scans (default: 400)")
    b.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the first allowed one)")
    b.set_defaults(func=_bench)


def _load(name: str):
    from glassmap.sim.world import WorldFileError, load_world

    try:
        return load_world(name)
    except WorldFileError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def _generate(args: argparse.Namespace) -> int:
    from glassmap.sim.generate import generate_world
    from glassmap.sim.seeds import split_of

    gw = generate_world(args.seed, args.kind)
    out = args.out or os.path.join("out", "worlds", f"gen-{gw.kind}-{gw.seed}.toml")
    path = gw.save(out)
    print(f"wrote {path}: {gw.kind}, seed {gw.seed} ({split_of(gw.seed)} split), loop {gw.loop_length:.0f} m, "
          f"route clearance {gw.clearance:.2f} m")
    if args.render:
        from glassmap.sim.render import render_world

        print(f"wrote {render_world(_load(str(path)), args.render)}")
    return 0


def _worlds(args: argparse.Namespace) -> int:
    import numpy as np

    from glassmap.sim.materials import MaterialKind
    from glassmap.sim.world import builtin_worlds

    for name in builtin_worlds():
        w = _load(name)
        counts = np.bincount(w.segment_kind, minlength=len(MaterialKind))
        mats = ", ".join(f"{k.name.lower()} {counts[k]}" for k in MaterialKind if counts[k])
        (x0, y0), (x1, y1) = w.bounds
        print(f"{name}: {w.description}")
        print(f"  {len(w.segments)} segments ({mats}); bounds x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m")
        for r, wp in w.routes.items():
            length = float(np.hypot(*np.diff(wp, axis=0).T).sum())
            star = " (default)" if r == w.default_route else ""
            print(f"  route {r}{star}: {len(wp)} waypoints, {length:.1f} m, clearance {w.route_clearance(r):.2f} m")
    return 0


def _run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from glassmap.sim.dataset import simulate_run
    from glassmap.sim.laser import world_laser_params
    from glassmap.sim.robot import OdometryNoise

    world = _load(args.world)
    route = args.route if args.route is not None else world.default_route
    if route not in world.routes:
        print(f"error: world {world.name!r} has no route {route!r}; routes: {sorted(world.routes)}", file=sys.stderr)
        return 2
    out = args.out or os.path.join("out", "sim", f"{world.name}-{route}-s{args.seed}.npz")
    laser = replace(world_laser_params(world), multi_echo=not args.no_multi_echo)
    run = simulate_run(world, route, seed=args.seed, laser_params=laser,
                       odom_noise=OdometryNoise.none() if args.perfect_odometry else OdometryNoise(),
                       max_v=args.max_v, max_omega=math.radians(args.max_omega_deg), progress=not args.no_progress)
    path = run.save(out, compress=not args.uncompressed)
    import numpy as np

    ok = np.isfinite(run.ranges)
    print(f"wrote {path}: world {run.world_name}, route {run.route_name}, seed {run.seed}, "
          f"{run.duration:.1f} s simulated, {run.n_scans} scans, {len(run.odom_stamps)} odometry samples; "
          f"{ok.mean() * 100:.1f} % beams returned, {run.is_glass[ok].mean() * 100:.1f} % of returns from glass, "
          f"{run.crossed_glass.mean() * 100:.1f} % of beams crossed glass")
    return 0


def _parse_pose(text: str):
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError
        x, y, yaw = (float(p) for p in parts)
    except ValueError:
        raise SystemExit(f"error: --pose must be 'x,y,yaw_deg' (three numbers), got {text!r}") from None
    return x, y, math.radians(yaw)


def _render(args: argparse.Namespace) -> int:
    world = _load(args.world)
    out = args.out or os.path.join("out", "sim", f"{world.name}-{args.what}.png")
    if args.what == "world":
        from glassmap.sim.render import render_world

        path = render_world(world, out)
    elif args.what == "blueprint":
        from glassmap.sim.blueprint import Blueprint

        bp = Blueprint.from_world(world, resolution=args.resolution)
        path = bp.save_png(out)
    else:
        import numpy as np

        from glassmap.sim.laser import simulate_scan
        from glassmap.sim.render import render_scan
        from glassmap.sim.robot import RobotParams, compose

        pose = (np.array(_parse_pose(args.pose)) if args.pose
                else compose(world.start_pose, np.asarray(RobotParams().laser_offset)))
        scan = simulate_scan(world, pose, np.random.default_rng(args.seed))
        path = render_scan(world, scan, out, color_by=args.color_by)
    print(f"wrote {path}")
    return 0


def _bench(args: argparse.Namespace) -> int:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[var] = "1"
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    cpu = args.cpu if args.cpu is not None else (allowed[0] if allowed else None)
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    from glassmap.sim.bench import bench_scan

    world = _load(args.world)
    if args.n < 10:
        print("error: -n must be at least 10", file=sys.stderr)
        return 2
    res = bench_scan(world, n=args.n)
    print(res.summary())
    print(f"pinned to CPU {cpu}; target <= 2 ms per scan: {'met' if res.median_ms <= 2.0 else 'NOT met'} (median)")
    return 0
