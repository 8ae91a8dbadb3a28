"""Bias of single scan matches against a map built from the TRUE poses (no map-building feedback).

The estimator's map (occupancy, sub-cell end points) is built from a simulated run's key scans (every 5 cm)
at their true laser poses; each key scan is matched, with the truth as prior, against the map of the key
scans before it (or, with --full-map, against the map of the whole run), then integrated. Prints the mean
match error in the robot frame (along the track, positive = ahead; sideways, positive = left; yaw); what
each scan shows that might predict it (range jumps, the match's reported sigma and information along the
track) and how each correlates with the error; where
the score itself peaks along the track (other axes at the truth) against the vertex of the parabola through
the scores one cell either side (the matcher's sub-lattice estimate); where the score pushes the pose along
the track at the true poses (the 10 cm bins of end points with the largest summed gradient: which features
cause a bias); the field's vector along the track at the exact end points (true pose and noise-free range,
so an exact field gives 0; the 10 cm bins with the largest sums: where the field is wrong); and the field's
vector to the wall along forward beams around their true end points (a field whose walls lie behind the
true surface pulls the robot forward). docs/pose.md, "Start-up bias" and "Where the forward match bias
comes from", has the findings.

Usage: .venv/bin/python scripts/pose_map_bias.py WORLD [--seconds 20] [--seed 0] [--route short]
           [--no-range-noise] [--map-true-ranges] [--match-true-ranges] [--full-map]
           [--field line_normals=0,pool=2] [--matcher voxel=0.1] [--refresh N | --incremental] [--dump X:Y]
           [--no-mirror] [--exact-field] [--refine]

--exact-field replaces, in this script only, the field the matcher's fine stage reads with the exact distance
to the world's walls (an oracle: what an exact map would give, at corners too); --refine moves each match
to the 3-D maximum of its score (of the exact field's with --exact-field), so that the matcher's sub-lattice
estimate and the field's own peak can be told apart.
Use validation worlds (seeds 1000-1999), built-in ones or tests/pose/data/*.toml, never test worlds.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numba
import numpy as np

from glassmap.pose import matcher as matcher_module
from glassmap.pose.estimator import HIT_LAYERS, EstimatorConfig, PoseEstimator
from glassmap.pose.field import FAR
from glassmap.pose.matcher import select_points
from glassmap.sim.dataset import simulate_run
from glassmap.sim.laser import world_laser_params
from glassmap.sim.world import load_world

EXACT_CUT = 0.2  # m: beyond it the exact field, as the estimator's, gives the floor
REFINE_STEP = np.array([0.002, 0.002, 0.0002])  # m, m, rad
REFINE_GRID = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), dtype=float).reshape(3, -1).T
REFINE_DESIGN = np.stack([np.ones(27), *REFINE_GRID.T, *(REFINE_GRID ** 2).T, REFINE_GRID[:, 0] * REFINE_GRID[:, 1],
                          REFINE_GRID[:, 0] * REFINE_GRID[:, 2], REFINE_GRID[:, 1] * REFINE_GRID[:, 2]], axis=1)
OFFSETS = np.linspace(-0.05, 0.05, 11)  # m along the beam around the true end point (field profile)
DENSE = np.arange(-0.01, 0.01001, 0.00025)  # m along the track around the true pose (where the score peaks)


def _args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--route", default="short")
    ap.add_argument("--no-range-noise", action="store_true", help="simulate the laser without range noise")
    ap.add_argument("--map-true-ranges", action="store_true", help="build the map from the noise-free ranges")
    ap.add_argument("--match-true-ranges", action="store_true", help="match the noise-free ranges")
    ap.add_argument("--full-map", action="store_true", help="build the whole run's map first, then match")
    ap.add_argument("--field", default="", help="FieldParams overrides, e.g. line_normals=0,pool=2")
    ap.add_argument("--matcher", default="", help="MatcherConfig overrides, e.g. voxel=0.1,max_points=300")
    ap.add_argument("--refresh", type=int, default=0, help="rebuild the field every N key scans (0: the estimator's)")
    ap.add_argument("--incremental", action="store_true",
                    help="update the field at every key scan (EstimatorConfig.field_incremental) instead")
    ap.add_argument("--dump", default="", help="X:Y (m): print the map and the field's vectors around this point")
    ap.add_argument("--no-mirror", action="store_true", help="simulate the laser without mirror images behind glass")
    ap.add_argument("--exact-field", action="store_true",
                    help="the matcher's fine stage scores the exact distance to the world's walls (oracle)")
    ap.add_argument("--refine", action="store_true", help="move each match to the 3-D maximum of its score")
    return ap.parse_args()


@numba.njit(cache=False)
def _exact_squared_distances(segs, px, py, c, s, ox, oy, res, tx, ty, scale, cut):
    """As ``matcher_jit.scaled_squared_distances``, from the exact distance of each moved point to the nearest
    of the wall segments ``segs`` (m, (m, 2, 2), in the field's frame); beyond ``cut`` (m) the far vector's."""
    out = np.empty((c.shape[0], tx.shape[0], px.shape[0]), np.float32)
    for k in range(c.shape[0]):
        kx, ky = (k if ox.shape[0] > 1 else 0), (k if oy.shape[0] > 1 else 0)
        for j in range(px.shape[0]):
            bx = c[k] * px[j] - s[k] * py[j] + ox[kx]
            by = s[k] * px[j] + c[k] * py[j] + oy[ky]
            for t in range(tx.shape[0]):
                qx, qy = bx + tx[t] * res, by + ty[t] * res
                best = FAR * FAR
                for i in range(segs.shape[0]):
                    ax, ay = segs[i, 0, 0], segs[i, 0, 1]
                    dx, dy = segs[i, 1, 0] - ax, segs[i, 1, 1] - ay
                    l2 = dx * dx + dy * dy
                    u = min(max(((qx - ax) * dx + (qy - ay) * dy) / l2, 0.0), 1.0) if l2 > 0 else 0.0
                    ex, ey = qx - ax - u * dx, qy - ay - u * dy
                    best = min(best, ex * ex + ey * ey)
                out[k, t, j] = np.float32(best if best <= cut * cut else FAR * FAR) * scale
    return out


def _use_exact_field(est: PoseEstimator, segs: np.ndarray) -> None:
    """Make the matcher's fine stage (this process only) score the exact distance to ``segs`` (m, map frame)."""
    def distances(vx, vy, px, py, c, s, ox, oy, res, off, margin, w, h, scale):
        ty = np.round(off / w)
        local = segs - np.asarray(est.field.origin)[None, None, :]
        return _exact_squared_distances(local, px, py, c, s, ox, oy, float(res), off - ty * w, ty, scale, EXACT_CUT)

    matcher_module.scaled_squared_distances = distances


def _score(est: PoseEstimator, pts: np.ndarray, w: np.ndarray, pose: np.ndarray, segs: np.ndarray | None) -> float:
    """The matcher's score of base-frame points ``pts`` at ``pose``: the field's, or the exact walls' ``segs``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    p = est.field.params
    if segs is not None:
        d2 = _exact_squared_distances(segs, np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                                      np.array([c]), np.array([s]), pose[:1], pose[1:2], 1.0, np.zeros(1),
                                      np.zeros(1), np.float32(-0.5 / p.sigma_hit ** 2), EXACT_CUT)[0, 0]
        return float(w @ np.log(np.exp(d2.astype(np.float64)) + p.p_floor))
    xy = pose[:2] + np.stack([c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]], axis=1)
    return float(w @ est.field.log_likelihood(xy))


def _refined(est: PoseEstimator, pts: np.ndarray, w: np.ndarray, pose: np.ndarray,
             segs: np.ndarray | None) -> np.ndarray:
    """``pose`` moved to the 3-D maximum of the score: quadratic fits over 3 x 3 x 3 poses 2 mm / 0.2 mrad apart,
    until the step is small; ``pose`` itself where the score does not curve down in every direction."""
    q = pose.copy()
    for _ in range(6):
        vals = np.array([_score(est, pts, w, q + g * REFINE_STEP, segs) for g in REFINE_GRID])
        coef = np.linalg.lstsq(REFINE_DESIGN, vals, rcond=None)[0]
        hess = np.array([[2 * coef[4], coef[7], coef[8]], [coef[7], 2 * coef[5], coef[9]],
                         [coef[8], coef[9], 2 * coef[6]]])
        if np.linalg.eigvalsh(hess).max() >= 0:
            return pose
        step = np.clip(-np.linalg.solve(hess, coef[1:4]), -3, 3)
        q = q + step * REFINE_STEP
        if np.all(np.abs(step) < 0.05):
            break
    return q


def _overrides(obj, text: str):
    """The dataclass ``obj`` with the numeric fields of ``text`` ("name=value,...") set."""
    for kv in filter(None, text.split(",")):
        k, v = kv.split("=")
        obj = replace(obj, **{k: type(getattr(obj, k))(float(v))})
    return obj


def main() -> int:
    args = _args()
    world = load_world(args.world)
    laser = world_laser_params(world)
    if args.no_range_noise:
        laser = replace(laser, range_noise=0.0, range_noise_slope=0.0)
    if args.no_mirror:
        laser = replace(laser, mirror_reflections=False)
    run = simulate_run(world, args.route, seed=args.seed, laser_params=laser)
    cfg = EstimatorConfig(laser_mount=tuple(run.params["robot"]["laser_offset"]), background_field=False)
    cfg = replace(cfg, likelihood=_overrides(cfg.likelihood, args.field), matcher=_overrides(cfg.matcher, args.matcher))
    if args.refresh:
        cfg = replace(cfg, field_refresh_scans=args.refresh)
    if args.incremental:
        cfg = replace(cfg, field_incremental=True)
    est = PoseEstimator(cfg)
    g = est.occupancy.grid
    segs = np.asarray(world.segments, dtype=np.float64) if args.exact_field else None
    if segs is not None:
        _use_exact_field(est, segs)

    def rebuild(xy):
        est.field.rebuild(est.occupancy, xy, tuple(g[k] for k in HIT_LAYERS))

    n = int(np.searchsorted(run.scan_stamps, args.seconds))
    keys, last = [], None
    for i in range(n):
        if last is None or np.hypot(*(run.scan_true_poses[i, :2] - last)) >= cfg.keyframe_distance:
            keys.append(i)
            last = run.scan_true_poses[i, :2]
    passes = [(False, True), (True, False)] if args.full_map else [(True, True)]
    errs, grad, prof, since, peaks, para, pred = [], {}, [], 0, [], [], []
    exact_err: dict[tuple, list] = {}  # per 10 cm bin: [sum of the field's along-track vector (m), count]
    for do_match, do_map in passes:
        if do_match and not do_map:
            rebuild(run.scan_true_poses[n // 2, :2])
        for i in keys:
            truth = run.scan_true_poses[i]
            scan = run.scan(i)
            measured = np.asarray(scan.ranges, dtype=np.float64)
            exact = np.where(np.isfinite(measured), np.asarray(run.true_range[i], dtype=np.float64), measured)
            lp = est.laser_pose_of(truth)
            if do_match and est.field.ready:
                ranges = exact if args.match_true_ranges else measured
                pts, w, idx = select_points(scan.angles, ranges, est.mount, cfg.matcher)
                res = est.matcher.match(est.field, pts, w, truth, np.diag([0.02 ** 2, 0.02 ** 2, 0.01 ** 2]))
                if res is not None and args.refine:
                    res = replace(res, pose=_refined(est, pts, w, res.pose, segs))
                c, s = np.cos(truth[2]), np.sin(truth[2])
                if res is not None:
                    d = res.pose - truth
                    errs.append((run.scan_stamps[i], c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]))
                    pred.append(_predictors(measured, res, np.array([c, s, 0.0]), cfg.likelihood.sigma_hit))
                a = lp[2] + scan.angles[idx]
                u = np.stack([np.cos(a), np.sin(a)], axis=1)
                pm = lp[:2] + ranges[idx][:, None] * u

                def along_scores(offsets):  # scores of the pose moved along the track (y and yaw at the truth)
                    return np.array([w @ est.field.log_likelihood(pm + dv * np.array([c, s])) for dv in offsets])

                peaks.append(DENSE[int(np.argmax(along_scores(DENSE)))])  # where the score itself peaks
                # the matcher's sub-lattice estimate: the vertex of a parabola through the lattice neighbours
                v3 = along_scores((-g.resolution, 0.0, g.resolution))
                den = v3[0] - 2 * v3[1] + v3[2]
                para.append(np.clip(0.5 * (v3[0] - v3[2]) / den, -0.5, 0.5) * g.resolution if den < 0 else np.nan)
                # the score's gradient along the track at the true pose, per end point, binned by position
                step = 0.002 * np.array([c, s])
                gr = (est.field.log_likelihood(pm + step) - est.field.log_likelihood(pm - step)) / 0.004
                for key, gv in zip(map(tuple, np.round(pm / 0.1).astype(int)), gr):
                    grad[key] = grad.get(key, 0.0) + gv
                # the field's vector along the track at the exact end points (0 for an exact field)
                tr = np.asarray(run.true_range[i], dtype=np.float64)[idx]
                real = np.isfinite(tr) & ~run.is_ghost[i][idx]
                pt = lp[:2] + tr[real, None] * u[real]
                vt = est.field.wall_vectors(pt)
                near = np.all(np.isfinite(vt), axis=1) & (np.hypot(*vt.T) < 0.06)
                for key, av in zip(map(tuple, np.round(pt[near] / 0.1).astype(int)), vt[near] @ np.array([c, s])):
                    acc = exact_err.setdefault(key, [0.0, 0])
                    acc[0] += av
                    acc[1] += 1
                # the field's vector along forward beams around their true end points (no mirror images)
                fwd = real & (np.cos(scan.angles[idx]) > 0.7)
                q = (lp[:2] + tr[fwd, None] * u[fwd])[None] + OFFSETS[:, None, None] * u[fwd][None]
                vq = est.field.wall_vectors(q.reshape(-1, 2)).reshape(len(OFFSETS), -1, 2)
                near = np.all(np.isfinite(vq), axis=(0, 2)) & (np.hypot(*vq[5].T) < 0.06)
                prof.append(np.sum(vq * u[fwd][None], axis=2)[:, near])
            if not do_map:
                continue
            map_ranges = exact if args.map_true_ranges else measured
            est.occupancy.integrate(lp, scan.angles, map_ranges, scan.geometry.range_max)
            est.ekf.pose = truth.copy()  # _store_hits places the end points at the filter's pose
            est._store_hits(scan.angles, map_ranges, scan.geometry.range_max)
            since += 1
            if not est.field.ready or (
                    np.max(np.abs(truth[:2] - est.field.center)) > cfg.field_recentre if cfg.field_incremental
                    else since >= cfg.field_refresh_scans):  # as the estimator: periodic, or re-centred
                rebuild(truth[:2])
                since = 0
            elif cfg.field_incremental:  # as the estimator: the field follows the map at every key scan
                est.field.refresh(est.occupancy, tuple(g[k] for k in HIT_LAYERS))
    e = np.array(errs)
    for lo, hi in ((0, args.seconds / 2), (args.seconds / 2, args.seconds), (0, args.seconds)):
        m = (e[:, 0] >= lo) & (e[:, 0] < hi)
        print(f"t {lo:4.1f}-{hi:4.1f} s: {m.sum():4d} matches, mean along {1000 * e[m, 1].mean():+6.2f} mm "
              f"(se {1000 * e[m, 1].std() / np.sqrt(max(m.sum(), 1)):.2f}), sideways {1000 * e[m, 2].mean():+6.2f} mm, "
              f"yaw {1000 * e[m, 3].mean():+6.3f} mrad; median {1000 * np.median(e[m, 1]):+.2f}, "
              f"trimmed (|e| < 1 cm, {np.sum(m & (np.abs(e[:, 1]) < 0.01))}) "
              f"{1000 * e[m & (np.abs(e[:, 1]) < 0.01), 1].mean():+.2f} mm", flush=True)
    _print_predictors(e[:, 1], np.array(pred))
    print(f"the score's own maximum along the track (other axes at the truth): mean {1000 * np.mean(peaks):+.2f} mm "
          f"(se {1000 * np.std(peaks) / np.sqrt(len(peaks)):.2f}); vertex of the parabola through +-1 cell "
          f"{1000 * np.nanmean(para):+.2f} mm")
    print(f"score gradient along the track at the true poses, summed over the run: {sum(grad.values()):+.0f} per m; "
          "largest 10 cm bins of end points:")
    for (bx, by), gv in sorted(grad.items(), key=lambda kv: -abs(kv[1]))[:12]:
        print(f"   ({bx / 10:6.1f}, {by / 10:6.1f}) m: {gv:+8.0f}")
    tot = sum(v[0] for v in exact_err.values()) / max(sum(v[1] for v in exact_err.values()), 1)
    print(f"field vector along the track at the exact end points (true pose, true range; 0 for an exact field): "
          f"mean {1000 * tot:+.2f} mm; largest 10 cm bins (sum, mm; mean):")
    for (bx, by), (sv, cv) in sorted(exact_err.items(), key=lambda kv: -abs(kv[1][0]))[:10]:
        print(f"   ({bx / 10:6.1f}, {by / 10:6.1f}) m: {1000 * sv:+8.1f} mm over {cv} points, "
              f"mean {1000 * sv / cv:+.2f} mm")
    pr = np.concatenate(prof, axis=1)
    print("field vector along forward beams (mm; positive: the wall lies further along the beam) "
          "at the true end point + s:")
    print("   " + "  ".join(f"s {100 * sv:+.0f} cm {1000 * pr[k].mean():+6.2f}" for k, sv in enumerate(OFFSETS)))
    if args.dump:
        _dump(est, np.array([float(v) for v in args.dump.split(":")]), rebuild)
    return 0


def _predictors(ranges: np.ndarray, res, along: np.ndarray, sigma_hit: float) -> tuple[float, float, float]:
    """What a single scan and its match show that could predict the match's bias: the number of range jumps
    (the nearer end point of neighbouring beams more than max(15 cm, 5 %) apart: occluding edges, convex
    corners), the match's reported standard deviation along the track (m) and the end points' information
    along the track (in end points squarely facing it)."""
    r = np.where(np.isfinite(ranges), ranges, np.inf)
    with np.errstate(invalid="ignore"):
        jump = np.abs(np.diff(r)) > np.maximum(0.15, 0.05 * np.minimum(r[:-1], r[1:]))
    info = np.where(np.isfinite(res.information), res.information, 0.0)
    jumps = float(np.sum(jump & np.isfinite(np.minimum(r[:-1], r[1:]))))
    return jumps, float(np.sqrt(along @ res.covariance @ along)), float(along @ info @ along) * sigma_hit ** 2


def _print_predictors(err: np.ndarray, pred: np.ndarray) -> None:
    names = ("range jumps per scan", "reported sigma along the track (mm)", "information along the track (points)")
    scale = (1.0, 1000.0, 1.0)
    ok = np.abs(err) < 0.05
    print("per match, what the scan shows (median; correlation with the match's error along the track): " + "; ".join(
        f"{n} {k * np.median(pred[ok, j]):.1f} ({np.corrcoef(err[ok], pred[ok, j])[0, 1]:+.2f})"
        for j, (n, k) in enumerate(zip(names, scale))) + f"; error rms {1000 * err[ok].std():.2f} mm")


def _dump(est: PoseEstimator, xy: np.ndarray, rebuild) -> None:
    """The 9 x 9 cells around xy: occupied (#) or not (.), end points counted, field vector (mm)."""
    g = est.occupancy.grid
    rebuild(xy)
    c0 = g.world_to_cell(xy)
    for iy in range(c0[1] + 4, c0[1] - 5, -1):
        row = []
        for ix in range(c0[0] - 4, c0[0] + 5):
            v = est.field.wall_vectors(g.cell_to_world(np.array([ix, iy]))[None])[0]
            occ = "#" if est.occupancy.log_odds[iy, ix] > est.field.params.occupied_log_odds else "."
            row.append(f"{occ}{int(g['pose_hit_n'][iy, ix]):3d} ({1000 * v[0]:+4.0f},{1000 * v[1]:+4.0f})")
        print(f"y {g.cell_to_world(np.array([0, iy]))[1]:+.3f} " + " ".join(row))
    xs = g.cell_to_world(np.stack([np.arange(c0[0] - 4, c0[0] + 5), np.zeros(9, dtype=int)], axis=1))[:, 0]
    print("x centres " + " ".join(f"{x:14.3f}" for x in xs))


if __name__ == "__main__":
    raise SystemExit(main())
