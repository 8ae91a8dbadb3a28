"""The compiled occupancy update (glassmap/grid_jit.py) gives the log-odds of the numpy ray walk it
replaced to the last bit: beams that cross each other's cells, hits, no-return beams, NaN, a protect mask,
growth of the grid, values clamped at the limits (only the cells a scan changes are clamped)."""

import numpy as np

from glassmap.grid import EDGE_BEAMS, EDGE_CHORD, MapGrid, OccupancyGrid, OccupancyParams, hit_margins
from tests.pose.synth import make_scan, room_with_corner


def numpy_hit_margins(c, s, ranges, hit, edge, surface):
    """``glassmap.grid.hit_margins`` before its kernel."""
    n, k = ranges.shape[0], EDGE_BEAMS
    margins = np.full(n, edge)
    if n > 2 * k and surface != edge:
        r = np.where(hit, ranges, np.nan)
        x, y = r * c, r * s
        with np.errstate(invalid="ignore"):
            inside = np.hypot(x[2 * k:] - x[:-2 * k], y[2 * k:] - y[:-2 * k]) < EDGE_CHORD
        margins[k:-k][inside] = surface
    return margins


def numpy_integrate(occ: OccupancyGrid, laser_pose, angles, ranges, range_max=30.0, protect=None):
    """``OccupancyGrid.integrate`` (and its ``_grow_for``) before the kernels (issue 19e), with the hit margins;
    returns also the end points (2, n) as ``integrate_scan``."""
    angles = np.asarray(angles, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    pose = np.asarray(laser_pose, dtype=np.float64)
    p = occ.params
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(ranges) & (ranges <= range_max)
    clear = hit | (np.isposinf(ranges) & (p.no_return_range > 0))
    free_len = np.where(hit, ranges.clip(0.0, p.max_free_range), p.no_return_range)
    c, s = np.cos(pose[2] + angles), np.sin(pose[2] + angles)
    u = np.stack([c, s], axis=1)
    ends = pose[:2] + u * np.where(hit, ranges, 0.0)[:, None]
    if not clear.any():
        return 0, ends.T
    reach = pose[:2] + u * free_len[:, None]
    pts = np.concatenate([ends[hit], reach[clear], pose[None, :2]])
    occ.grid.ensure_contains(pts.min(axis=0) - 1.0, pts.max(axis=0) + 1.0)
    g = occ.grid
    w = g.shape[1]
    if callable(protect):
        protect = protect()
    step = 0.7 * g.resolution
    margins = numpy_hit_margins(c, s, ranges, hit, max(p.hit_margin, g.resolution),
                                max(p.surface_margin, g.resolution))
    lengths = free_len[clear] - np.where(hit[clear], margins[clear], 0.0)
    counts = np.ceil(np.maximum(lengths, 0.0) / step).astype(np.int64)
    lo = occ.log_odds
    total = int(counts.sum())
    if total > 0:
        beam = np.repeat(np.arange(counts.size), counts)
        t = (np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)).astype(np.float32) * step
        fx = np.float32((pose[0] - g.origin[0]) / g.resolution)
        fy = np.float32((pose[1] - g.origin[1]) / g.resolution)
        ix = np.floor(fx + (c[clear] / g.resolution).astype(np.float32)[beam] * t).astype(np.int64)
        iy = np.floor(fy + (s[clear] / g.resolution).astype(np.float32)[beam] * t).astype(np.int64)
        flat = iy * w + ix
        if protect is not None:
            flat = flat[~protect.ravel()[flat]]
        lo.ravel()[flat] += p.l_free
    if hit.any():
        hc = g.world_to_cell(ends[hit])
        lo.ravel()[np.unique(hc[:, 1] * w + hc[:, 0])] += p.l_occ
    np.clip(lo, p.l_min, p.l_max, out=lo)
    return int(clear.sum()), ends.T


def test_integrate_equals_the_numpy_ray_walk_to_the_bit():
    segs = room_with_corner()
    rng = np.random.default_rng(11)
    for params in (OccupancyParams(), OccupancyParams(no_return_range=2.5, max_free_range=3.0, l_free=-0.37,
                                                      l_occ=0.91, l_min=-1.3, l_max=1.7, hit_margin=0.0)):
        a = OccupancyGrid(MapGrid(shape=(60, 80), origin=(-1.5, -2.0), grow_step_m=2.0), params)
        b = OccupancyGrid(MapGrid(shape=(60, 80), origin=(-1.5, -2.0), grow_step_m=2.0), params)
        for i in range(14):
            pose = np.array([rng.uniform(-2.5, 2.5), rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi)])
            scan = make_scan(segs, pose, noise=0.02, rng=rng)
            r = scan.ranges.copy()
            r[rng.random(r.size) < 0.05] = np.nan
            r[rng.random(r.size) < 0.05] = np.inf
            r[rng.random(r.size) < 0.02] *= 8.0  # long beams: growth, and beyond max_free_range
            # a protect mask (taken after the grid grew) on some scans, the same for both
            mask = (lambda g, seed=i: np.random.default_rng(seed).random(g.shape) < 0.3) if i % 2 else None
            n_a, ends_a = a.integrate_scan(pose, scan.angles, r, 20.0, protect=mask and (lambda: mask(a.grid)))
            n_b, ends_b = numpy_integrate(b, pose, scan.angles, r, 20.0, protect=mask and (lambda: mask(b.grid)))
            assert n_a == n_b and a.grid.shape == b.grid.shape
            np.testing.assert_array_equal(ends_a, ends_b)
            np.testing.assert_array_equal(a.grid.origin, b.grid.origin)
            np.testing.assert_array_equal(a.log_odds, b.log_odds)
            assert a._seen.size == a.log_odds.size and not a._seen.any()  # the scratch is left clean
        assert (a.log_odds == params.l_min).any() and (a.log_odds == params.l_max).any()  # limits reached


def test_hit_margins_equal_numpy_to_the_bit():
    rng = np.random.default_rng(5)
    for n in (0, 5, 6, 7, 40, 1081):
        a = np.sort(rng.uniform(-2.4, 2.4, n))
        c, s = np.cos(a), np.sin(a)
        ranges = rng.uniform(0.1, 3.0, n)
        ranges[rng.random(n) < 0.3] = ranges[0] if n else 0.0  # flat stretches: neighbours close together
        hit = rng.random(n) < 0.8
        ranges[~hit & (rng.random(n) < 0.5)] = np.nan
        for edge, surface in ((0.2, 0.1), (0.2, 0.2), (0.05, 0.3)):
            np.testing.assert_array_equal(hit_margins(c, s, ranges, hit, edge, surface),
                                          numpy_hit_margins(c, s, ranges, hit, edge, surface))


def test_the_mappers_beam_masks_equal_numpy():
    """``ranged_beams`` and ``classified_beams`` (GlassMapper.classify) give the masks and counts of the numpy
    expressions they replaced."""
    from glassmap.grid_jit import classified_beams, ranged_beams

    rng = np.random.default_rng(3)
    for n in (0, 1, 50, 1081):
        r = rng.uniform(-0.5, 35.0, n)
        for v, share in ((np.nan, 0.1), (np.inf, 0.05), (-np.inf, 0.02), (0.1, 0.02), (30.0, 0.02)):
            r[rng.random(n) < share] = v
        inc = np.where(rng.random(n) < 0.7, rng.uniform(0, 1.5, n), np.nan)
        inten = rng.uniform(0, 5000, n)
        inten[rng.random(n) < 0.1] = np.nan
        inten[rng.random(n) < 0.05] = np.inf
        ranged = np.isfinite(r) & (r >= 0.1) & (r <= 30.0)
        rr, n_ranged, n_nan = ranged_beams(r, 0.1, 30.0)
        np.testing.assert_array_equal(rr, np.where(ranged, r, np.nan))
        assert (n_ranged, n_nan) == (np.count_nonzero(ranged), np.count_nonzero(np.isnan(r)))
        use, n_angle, n_bad, n_use = classified_beams(inc, inten, r)
        np.testing.assert_array_equal(use, np.isfinite(inc) & np.isfinite(inten))
        assert (n_angle, n_bad, n_use) == (np.count_nonzero(np.isfinite(inc)),
                                           np.count_nonzero(~np.isfinite(inten) & ~np.isnan(r)), np.count_nonzero(use))


def test_bounds_are_numpys_min_and_max():
    from glassmap.grid_jit import bounds

    rng = np.random.default_rng(8)
    for n in (1, 2, 7, 300):
        x, y = rng.normal(size=n) * 10, rng.normal(size=n) * 10
        np.testing.assert_array_equal(bounds(x, y), [x.min(), y.min(), x.max(), y.max()])
        x[n // 2] = np.nan
        assert np.isnan(bounds(x, y)[[0, 2]]).all() and not np.isnan(bounds(x, y)[[1, 3]]).any()
