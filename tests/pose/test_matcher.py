"""Correlative matcher: recovers a known offset; the covariance follows the geometry (corridor vs corner)."""

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid, OccupancyParams
from glassmap.pose.field import FieldParams, LikelihoodField
from glassmap.pose.matcher import CorrelativeMatcher, MatcherConfig, select_points
from tests.pose.synth import box, corridor, make_scan, room_with_corner

PRIOR = np.diag([0.1 ** 2, 0.1 ** 2, np.radians(2.0) ** 2])


def _map_from(segments, poses, center=np.zeros(2)):
    """Likelihood field of the occupancy from noisy scans taken at the true ``poses`` (walls at cell centres;
    beams clear up to one cell short of their end points, so that a wall is one cell thick and its cell
    centres lie on the surface)."""
    occ = OccupancyGrid(MapGrid(), OccupancyParams(hit_margin=0.0, surface_margin=0.0))
    for i, p in enumerate(poses):
        s = make_scan(segments, p, noise=0.01, rng=np.random.default_rng(100 + i))
        occ.integrate(p, s.angles, s.ranges)
    fld = LikelihoodField()
    fld.rebuild(occ, center)
    return fld


def _map_of(segments, pose=np.zeros(3), n=3):
    """A map from n scans around ``pose`` (a few cm and a degree apart)."""
    return _map_from(segments, [pose + np.array([0.03 * i, -0.02 * i, np.radians(0.7) * i]) for i in range(n)],
                     pose[:2])


def _match(fld, segments, true_pose, prior_pose=np.zeros(3), config=MatcherConfig(), seed=7):
    s = make_scan(segments, true_pose, noise=0.01, rng=np.random.default_rng(seed))
    m = CorrelativeMatcher(config)
    pts, w, _ = select_points(s.angles, s.ranges, np.zeros(3), m.config)
    return m.match(fld, pts, w, prior_pose, PRIOR)


@pytest.mark.parametrize("offset", [(0.13, -0.08, 2.0), (-0.21, 0.17, -3.5), (0.0, 0.3, 0.0)])
def test_recovers_known_offset(offset):
    segs = room_with_corner()
    fld = _map_of(segs)
    true = np.array([offset[0], offset[1], np.radians(offset[2])])
    r = _match(fld, segs, true)
    assert r is not None
    assert np.hypot(*(r.pose[:2] - true[:2])) < 0.02  # well below one 5 cm cell
    assert abs(r.pose[2] - true[2]) < np.radians(0.5)
    # the error is inside the reported uncertainty (3 sigma)
    e = r.pose - true
    assert e @ np.linalg.solve(r.covariance, e) < 14.2  # chi-square 3 dof, 99.7 %


def test_corridor_covariance_is_elongated_along_the_corridor():
    segs = corridor(length=60.0, half_width=1.0)
    fld = _map_of(segs)
    r = _match(fld, segs, np.array([0.1, 0.05, np.radians(1.0)]))
    assert r is not None
    vals, vecs = np.linalg.eigh(r.covariance[:2, :2])
    major = vecs[:, 1]
    assert abs(major[0]) > 0.95  # the long axis is the corridor's (x)
    assert vals[1] / vals[0] > 5.0
    assert np.sqrt(r.covariance[1, 1]) < 0.04  # across the corridor: well constrained
    assert abs(r.pose[1] - 0.05) < 0.02


def test_corner_covariance_is_small_and_round():
    segs = np.array([[2.0, -4.0, 2.0, 2.0], [-4.0, 2.0, 2.0, 2.0]])  # an L-shaped corner ahead-left
    fld = _map_of(segs)
    r = _match(fld, segs, np.array([0.06, -0.04, np.radians(0.5)]))
    assert r is not None
    vals = np.linalg.eigvalsh(r.covariance[:2, :2])
    assert np.sqrt(vals[1]) < 0.04
    assert vals[1] / vals[0] < 3.0
    # against a corridor mapped while driving along it: a map of a few scans from one spot has dotted far
    # walls, whose ripples make a narrow (and wrong) along-track peak
    driven = _map_from(corridor(60.0), [np.array([x, 0.0, 0.0]) for x in np.arange(-5.0, 5.01, 0.5)])
    corr = _match(driven, corridor(60.0), np.array([0.06, -0.04, np.radians(0.5)]))
    assert vals[1] < 0.33 * np.linalg.eigvalsh(corr.covariance[:2, :2])[1]


def test_sharp_match_covariance_is_the_curvature_of_the_scores():
    """In a box whose walls lie on cell centres (noise-free scans), the score near the peak is
    -sum_j d_j^2 / (2 sigma_hit^2), so the tempered distribution has standard deviation
    sigma_hit / sqrt(beta N) along x with N the end points on the walls facing x (likewise y): a few mm,
    far below the 5 cm lattice step, and not a fixed number."""
    segs = box(-3.025, -2.025, 2.975, 1.975)
    fld = _map_from(segs, [np.array([0.1 * i, -0.05 * i, 0.0]) for i in range(5)])
    true = np.array([0.012, -0.007, 0.002])
    s = make_scan(segs, true)
    m = CorrelativeMatcher()
    pts, w, _ = select_points(s.angles, s.ranges, np.zeros(3), m.config)
    r = m.match(fld, pts, w, np.zeros(3), np.diag([0.05 ** 2, 0.05 ** 2, 0.02 ** 2]))
    c, sn = np.cos(true[2]), np.sin(true[2])
    wp = true[:2] + pts @ np.array([[c, sn], [-sn, c]])
    n_x = np.sum(np.minimum(abs(wp[:, 0] + 3.025), abs(wp[:, 0] - 2.975)) < 0.01)
    n_y = np.sum(np.minimum(abs(wp[:, 1] + 2.025), abs(wp[:, 1] - 1.975)) < 0.01)
    beta = min(1.0, m.config.independent_points / w.sum())
    expected = FieldParams().sigma_hit / np.sqrt(beta * np.array([n_x, n_y]))
    assert np.sqrt(np.diag(r.covariance)[:2]) == pytest.approx(expected, rel=0.15)
    assert abs(r.pose - true).max() < 0.003


def test_no_match_on_empty_map_or_too_few_points():
    segs = room_with_corner()
    empty = LikelihoodField()
    empty.rebuild(OccupancyGrid(MapGrid()), np.zeros(2))
    assert not empty.ready
    assert _match(empty, segs, np.zeros(3)) is None
    fld = _map_of(segs)
    m = CorrelativeMatcher()
    assert m.match(fld, np.zeros((3, 2)), np.ones(3), np.zeros(3), PRIOR) is None


def test_select_points_drops_invalid_and_thins():
    cfg = MatcherConfig(max_points=50)
    angles = np.linspace(-1, 1, 400)
    ranges = np.full(400, 3.0)
    ranges[:10] = np.nan
    ranges[10:20] = np.inf
    ranges[20:30] = 0.05  # below range_min
    pts, w, idx = select_points(angles, ranges, np.array([0.1, 0.0, 0.0]), cfg)
    assert 0 < len(pts) <= 50 and idx.min() >= 30
    assert np.allclose(np.hypot(pts[:, 0] - 0.1, pts[:, 1]), 3.0)
    weights = np.ones(400)
    weights[200:] = 0.0
    _, _, idx = select_points(angles, ranges, np.zeros(3), cfg, weights)
    assert idx.max() < 200


def test_field_is_floor_away_from_walls_and_peak_on_walls():
    fld = _map_of(room_with_corner())
    params = FieldParams()
    arr = fld.fine.reshape(fld.shape)
    assert arr.max() == pytest.approx(np.log(1 + params.p_floor), abs=1e-5)
    assert arr.min() == pytest.approx(np.log(params.p_floor), abs=1e-3)
    coarse = fld.coarse.reshape(fld.shape)
    assert (coarse >= arr - 1e-6).all()  # block maximum is an upper bound


def test_which_beams_are_used_does_not_depend_on_their_own_range_noise():
    """Thinning picks beams by index with a stride taken from the neighbours' ranges: changing the ranges of
    the even beams only (their noise) leaves the choice among the even beams unchanged. (Picking "the first
    beam of each voxel" keeps beams whose noise has one sign: a yaw bias per match.)"""
    cfg = MatcherConfig(max_points=10_000)
    angles = np.radians(np.linspace(-135, 135, 1081))
    rng = np.random.default_rng(0)
    ranges = 2.0 + 6.0 * rng.random(1081)  # strides from 1 to 8 beams
    _, _, idx = select_points(angles, ranges, np.zeros(3), cfg)
    noisy = ranges.copy()
    noisy[::2] += rng.normal(0.0, 0.05, noisy[::2].shape)
    _, _, idx2 = select_points(angles, noisy, np.zeros(3), cfg)
    assert np.array_equal(idx[idx % 2 == 0], idx2[idx2 % 2 == 0])
    assert 100 < idx.size < 600  # thinned: about one beam per 8 cm of arc


def test_score_hessian_stencil_is_the_per_call_offsets():
    from glassmap.pose.matcher import _HESSIAN_STENCIL

    rng = np.random.default_rng(7)
    for _ in range(200):
        h, pose = rng.uniform(1e-5, 0.02, 3), rng.normal(size=3)
        pose[rng.integers(3)] = -0.0
        eye = np.eye(3) * h
        i, j = np.triu_indices(3, 1)
        offs = [np.zeros(3)] + [sg * eye[k] for k in range(3) for sg in (1, -1)]
        offs += [a * eye[k] + b * eye[m] for k, m in zip(i, j) for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
        assert (pose + np.array(offs)).tobytes() == (pose + _HESSIAN_STENCIL * h).tobytes()


def test_p90_and_median_equal_numpy_percentile_and_median():
    from glassmap.pose.matcher import _p90_and_median

    rng = np.random.default_rng(9)
    for n in list(range(1, 40)) + [199, 200, 201, 1000]:
        for _ in range(30):
            r = rng.uniform(0.3, 15.0, n) * rng.choice([1.0, 1e-3])
            if n > 3 and rng.random() < 0.3:
                r[: n // 3] = r[-1]  # ties
            p90, med = _p90_and_median(r)
            assert np.float64(p90).tobytes() == np.float64(np.percentile(r, 90)).tobytes()
            assert np.float64(med).tobytes() == np.float64(np.median(r)).tobytes()
    r = np.array([1.0, np.nan, 2.0])
    assert np.isnan(_p90_and_median(r)[0]) and np.isnan(_p90_and_median(r)[1])


def test_median_equals_numpy_median():
    from glassmap.pose.matcher import _median

    rng = np.random.default_rng(14)
    for n in list(range(1, 30)) + [1080, 1081]:
        for _ in range(20):
            x = np.abs(np.diff(rng.uniform(-2.4, 2.4, n + 1)))
            if rng.random() < 0.5:
                x = np.abs(np.diff(-2.356 + 0.0043633 * np.arange(n + 1)))  # a laser's increments: ties
            assert np.float64(_median(x)).tobytes() == np.float64(np.median(x)).tobytes()
    assert np.isnan(_median(np.array([1.0, np.nan])))


def test_select_points_keeps_the_beams_it_kept_before():
    # the stride rule with the earlier np.clip / np.median code, as a reference
    rng = np.random.default_rng(15)
    angles = -2.356 + 0.0043633 * np.arange(1081)
    cfg = MatcherConfig()
    for _ in range(50):
        ranges = rng.uniform(0.1, 20.0, 1081) * rng.choice([1.0, 0.1], 1081)
        ranges[rng.random(1081) < 0.05] = np.inf
        ranges[rng.random(1081) < 0.02] = np.nan
        idx = np.flatnonzero(np.isfinite(ranges) & (ranges >= cfg.range_min) & (ranges <= cfg.range_max))
        inc = float(np.median(np.abs(np.diff(angles))))
        lo, hi = ranges[np.maximum(idx - 1, 0)], ranges[np.minimum(idx + 1, 1080)]
        lo = np.where(np.isfinite(lo) & (idx > 0), lo, np.nan)
        hi = np.where(np.isfinite(hi) & (idx < 1080), hi, np.nan)
        both = np.isfinite(lo) & np.isfinite(hi)
        rs = np.where(both, 0.5 * (lo + hi), np.where(np.isfinite(lo), lo, np.where(np.isfinite(hi), hi, ranges[idx])))
        k = np.clip(np.rint(np.log2(cfg.voxel / (np.maximum(rs, 1e-3) * max(inc, 1e-9)))), 0, 6).astype(np.int64)
        ref = idx[(idx & ((1 << k) - 1)) == 0]
        if ref.size > cfg.max_points:
            ref = ref[np.linspace(0, ref.size - 1, cfg.max_points).astype(np.int64)]
        assert np.array_equal(select_points(angles, ranges, np.zeros(3), cfg)[2], ref)


def test_clamp_equals_np_clip_of_one_number():
    from glassmap.pose.matcher import _clamp

    rng = np.random.default_rng(16)
    xs = list(rng.normal(0, 1, 2000)) + [0.0, -0.0, -0.5, 0.5, np.inf, -np.inf]
    for x in xs:
        for lo, hi in ((-0.5, 0.5), (0.15, 0.5), (np.radians(0.1), np.radians(0.25))):
            assert np.float64(_clamp(x, lo, hi)).tobytes() == np.float64(np.clip(x, lo, hi)).tobytes()
    assert np.isnan(_clamp(np.nan, 0.0, 1.0))
