"""Laser model: known geometry gives known ranges, incidence angles and intensities; glass returns only near
normal incidence and otherwise the beam ranges what is behind; distractors and noise as parameterised."""

import math

import numpy as np
import pytest

from glassmap.sim.laser import LaserParams, SimScan, cast_pairs, simulate_scan
from glassmap.sim.materials import MaterialKind
from glassmap.sim.world import load_world, parse_world
from glassmap.types import LaserGeometry

EXACT = LaserParams(intensity_noise=0.0, range_noise=0.0, range_noise_slope=0.0, dropout_prob=0.0,
                    saturation=1e12)
GEOM = LaserGeometry()
ANG = GEOM.angles


def world_of(*segs: tuple[tuple[float, float], tuple[float, float], str], materials: str = ""):
    body = "".join(f"[[segments]]\na = [{a[0]}, {a[1]}]\nb = [{b[0]}, {b[1]}]\nmaterial = \"{m}\"\n"
                   for a, b, m in segs)
    return parse_world(materials + body)


def beam(deg: float) -> int:
    return int(round((math.radians(deg) - GEOM.angle_min) / GEOM.angle_increment))


def scan(world, pose=(0.0, 0.0, 0.0), params=EXACT, seed=0) -> SimScan:
    return simulate_scan(world, np.array(pose, dtype=float), np.random.default_rng(seed), params)


def test_wall_ranges_incidence_and_diffuse_intensity():
    w = world_of(((5.0, -20.0), (5.0, 20.0), "wall"))
    s = scan(w)
    for deg in (0.0, 10.0, -30.0, 45.0, 60.0):
        k = beam(deg)
        th = ANG[k]
        assert s.ranges[k] == pytest.approx(5.0 / math.cos(th), abs=1e-9)
        assert s.true_range[k] == pytest.approx(5.0 / math.cos(th), abs=1e-9)
        assert s.incidence[k] == pytest.approx(abs(th), abs=1e-9)
        assert s.material[k] == MaterialKind.WALL and not s.is_glass[k] and not s.crossed_glass[k]
        # I = K * rho * cos^k(alpha) * (r0 / max(r, r_min))^beta with K 6000, rho 0.65, k 1, r0 1, beta 1
        assert s.intensities[k] == pytest.approx(6000 * 0.65 * math.cos(th) / (5.0 / math.cos(th)), rel=1e-9)
    # beyond atan(20 / 5) = 76 deg the wall is missed: no return
    assert np.isinf(s.ranges[beam(80.0)]) and s.material[beam(80.0)] == -1
    assert np.isnan(s.incidence[beam(80.0)])


def test_intensity_is_flat_below_near_range_and_saturates():
    w = world_of(((0.3, -5.0), (0.3, 5.0), "wall"))
    s = scan(w)
    assert s.intensities[beam(0)] == pytest.approx(6000 * 0.65 * (1 / 0.5), rel=1e-9)
    s = scan(w, params=LaserParams(intensity_noise=0.0, saturation=5000.0))
    assert s.intensities[beam(0)] == 5000.0


def test_pose_and_yaw_rotate_the_scan():
    w = world_of(((5.0, -20.0), (5.0, 20.0), "wall"))
    s = scan(w, pose=(1.0, 2.0, math.pi / 2))  # wall is now on the laser's right, 4 m away
    k = beam(-90.0)
    assert s.ranges[k] == pytest.approx(4.0, abs=1e-9)
    assert s.incidence[k] == pytest.approx(0.0, abs=1e-6)
    assert np.isinf(s.ranges[beam(0.0)])


def test_sweep_motion_takes_each_beam_from_where_the_laser_is():
    """Moving 0.3 m towards a wall at x = 5 during the sweep: the first beam (-135 deg) is taken at the start
    pose, the last (+135 deg) 0.3 m closer; a beam in the middle about half way. Standing still, the swept
    scan equals the single-pose scan."""
    w = world_of(((5.0, -20.0), (5.0, 20.0), "wall"), ((-5.0, -20.0), (-5.0, 20.0), "wall"))
    start, end = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.0, 0.0])
    moving = simulate_scan(w, start, np.random.default_rng(0), EXACT, end_pose=end, sweep_chunks=GEOM.n_beams)
    for k in (0, GEOM.n_beams - 1):
        x = start[0] + k / (GEOM.n_beams - 1) * 0.3
        wall = 5.0 if math.cos(ANG[k]) > 0 else -5.0
        assert moving.true_range[k] == pytest.approx((wall - x) / math.cos(ANG[k]), abs=1e-9)
    k = beam(0.0)
    assert moving.true_range[k] == pytest.approx(5.0 - 0.15, abs=1e-3)
    still = simulate_scan(w, start, np.random.default_rng(0), EXACT, end_pose=start)
    np.testing.assert_allclose(still.true_range, scan(w).true_range, atol=1e-9)


def test_segment_across_the_back_of_the_scanner():
    # x = -1 from y -5 to 5 spans bearings -101..+101 deg through 180: only the outer beams see it
    w = world_of(((-1.0, -5.0), (-1.0, 5.0), "wall"))
    s = scan(w)
    seen = np.isfinite(s.ranges)
    expect = np.abs(ANG) > math.atan2(5.0, -1.0) + 1e-9
    np.testing.assert_array_equal(seen, expect)
    np.testing.assert_allclose(s.ranges[seen], -1.0 / np.cos(ANG[seen]), rtol=1e-9)


def test_nearest_surface_wins_and_matches_brute_force_in_office():
    w = load_world("office")
    rng = np.random.default_rng(3)
    a = w.segments[:, 0]
    e = w.segments[:, 1] - a
    for _ in range(10):
        pose = np.array([rng.uniform(1, 35), rng.uniform(0.5, 1.9), rng.uniform(-math.pi, math.pi)])
        b, sid, t, _ = cast_pairs(w, pose, GEOM, max_range=60.0)
        first = np.full(GEOM.n_beams, np.inf)
        np.minimum.at(first, b, t)
        # brute force: every beam against every segment
        th = pose[2] + ANG
        d = np.stack([np.cos(th), np.sin(th)], 1)[:, None, :]
        ap = (a - pose[:2])[None]
        den = d[..., 0] * e[None, :, 1] - d[..., 1] * e[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = (ap[..., 0] * e[None, :, 1] - ap[..., 1] * e[None, :, 0]) / den
            uu = (ap[..., 0] * d[..., 1] - ap[..., 1] * d[..., 0]) / den
        tt = np.where((tt > 1e-9) & (uu >= 0) & (uu <= 1), tt, np.inf).min(axis=1)
        tt = np.where(tt <= 60.0, tt, np.inf)
        np.testing.assert_allclose(first, tt, rtol=1e-9)


GLASS_WORLD = world_of(((3.0, -30.0), (3.0, 30.0), "glass"), ((6.0, -30.0), (6.0, 30.0), "wall"))


def test_glass_returns_its_peak_at_normal_incidence():
    s = scan(GLASS_WORLD, params=LaserParams(intensity_noise=0.0, range_noise=0.0, range_noise_slope=0.0,
                                             dropout_prob=0.0))
    k = beam(0.0)
    assert s.is_glass[k] and s.material[k] == MaterialKind.GLASS
    assert s.ranges[k] == pytest.approx(3.0)
    assert s.intensities[k] == LaserParams().saturation  # very bright: saturates
    # multi-echo: the wall behind is the last echo
    assert s.echo_ranges[k, 0] == pytest.approx(3.0) and s.echo_ranges[k, 1] == pytest.approx(6.0)


def test_glass_is_transparent_away_from_normal_and_the_wall_behind_is_ranged():
    s = scan(GLASS_WORLD)
    for deg in (20.0, 35.0, -50.0, 60.0):
        k = beam(deg)
        th = ANG[k]
        # two passes of 0.92, with the Schlick angle factor (1 - R(alpha)) / (1 - R0), R0 = 0.04
        refl = 0.04 + 0.96 * (1 - math.cos(th)) ** 5
        T2 = (0.92 * (1 - refl) / 0.96) ** 2
        assert not s.is_glass[k] and s.crossed_glass[k]
        assert s.material[k] == MaterialKind.WALL
        assert s.ranges[k] == pytest.approx(6.0 / math.cos(th), abs=1e-9)
        assert s.incidence[k] == pytest.approx(abs(th), abs=1e-9)
        assert s.intensities[k] == pytest.approx(T2 * 6000 * 0.65 * math.cos(th) ** 2 / 6.0, rel=1e-9)
        assert np.isnan(s.echo_ranges[k, 1])


def test_glass_returns_only_inside_a_window_that_shrinks_with_distance():
    p = LaserParams()
    near = world_of(((1.0, -30.0), (1.0, 30.0), "glass"))
    far = world_of(((10.0, -30.0), (10.0, 30.0), "glass"))
    for w, r in ((near, 1.0), (far, 10.0)):
        hits = np.zeros(GEOM.n_beams)
        for seed in range(60):
            s = scan(w, params=p, seed=seed)
            hits += s.is_glass
            assert np.all(s.incidence[s.is_glass] < math.radians(16.0))
        rate = hits / 60
        alpha = np.abs(ANG)  # incidence on a wall facing the laser
        window = max(p.glass_window * r ** -p.glass_window_exponent, p.glass_window_min)
        assert rate[alpha > window + math.radians(1.5)].max() == 0.0  # no return: passes through
        assert rate[alpha < math.radians(0.3)].min() == 1.0  # the specular peak always returns
        mid = (alpha > 0.4 * window) & (alpha < 0.6 * window)
        expect = p.glass_return_prob * (1 - (0.5) ** 2)
        if r == 1.0:
            assert rate[mid].mean() == pytest.approx(expect, abs=0.08)
    # window: about 15 deg at 1 m, a few degrees at 10 m
    assert p.glass_window == pytest.approx(math.radians(15))
    assert math.degrees(p.glass_window * 10 ** -p.glass_window_exponent) == pytest.approx(3.0, abs=0.1)


def test_peak_is_a_few_beams_wide():
    s = scan(world_of(((5.0, -30.0), (5.0, 30.0), "glass")), params=LaserParams(glass_return_prob=0.0))
    bright = np.flatnonzero(s.is_glass)
    assert 3 <= bright.size <= 9  # within about +-1 deg of the normal at 0.25 deg per beam
    assert np.all(np.degrees(s.incidence[bright]) <= 1.1)


def test_two_panes_attenuate_twice():
    w = world_of(((2.0, -30.0), (2.0, 30.0), "glass"), ((3.0, -30.0), (3.0, 30.0), "glass"),
                 ((6.0, -30.0), (6.0, 30.0), "wall"))
    s = scan(w, params=LaserParams(intensity_noise=0.0, range_noise=0.0, range_noise_slope=0.0,
                                   dropout_prob=0.0, saturation=1e12, glass_fresnel_r0=None))
    k = beam(40.0)
    th = ANG[k]
    assert s.intensities[k] == pytest.approx(0.92 ** 4 * 6000 * 0.65 * math.cos(th) ** 2 / 6.0, rel=1e-9)
    assert s.crossed_glass[k]


def test_glass_is_harder_to_see_through_at_grazing_incidence():
    s = scan(world_of(((1.0, -30.0), (1.0, 30.0), "glass"), ((2.0, -30.0), (2.0, 30.0), "wall")))
    wall = scan(world_of(((2.0, -30.0), (2.0, 30.0), "wall")))
    with np.errstate(invalid="ignore"):  # 0 / 0 where neither returns
        ratio = s.intensities / wall.intensities
    assert ratio[beam(20)] == pytest.approx(0.92 ** 2, rel=0.01)
    refl = 0.04 + 0.96 * (1 - math.cos(ANG[beam(72)])) ** 5
    assert ratio[beam(72)] == pytest.approx((0.92 * (1 - refl) / 0.96) ** 2, rel=1e-6)
    assert ratio[beam(72)] < 0.75 * 0.92 ** 2
    assert np.all(np.diff(ratio[beam(20):beam(72)]) <= 1e-12)  # darker and darker towards grazing


def test_specular_distractors_and_retroreflector():
    metal = scan(world_of(((3.0, -30.0), (3.0, 30.0), "metal")))
    assert metal.intensities[beam(0)] > 20 * metal.intensities[beam(20)]  # bright lobe near normal
    assert np.isfinite(metal.ranges[beam(45)])  # but unlike glass it returns at every angle
    assert metal.intensities[beam(2)] > 0.5 * metal.intensities[beam(0)]  # lobe a few degrees wide
    retro = scan(world_of(((3.0, -30.0), (3.0, 30.0), "retro")))
    wall = scan(world_of(((3.0, -30.0), (3.0, 30.0), "wall")))
    assert retro.intensities[beam(60)] > 2 * wall.intensities[beam(0)]  # bright at every angle


def test_dark_material_sometimes_gives_no_return():
    w = world_of(((2.0, -30.0), (2.0, 30.0), "dark"))
    s = scan(w, params=LaserParams(dropout_prob=0.0))
    sel = np.abs(ANG) < math.radians(30)
    frac = np.isinf(s.ranges[sel]).mean()
    assert frac == pytest.approx(0.15, abs=0.06)
    assert np.all(s.material[sel] == MaterialKind.DARK)  # truth still names what the beam ended on


def test_range_noise_and_dropouts_follow_their_parameters():
    w = world_of(((10.0, -100.0), (10.0, 100.0), "wall"))
    p = LaserParams(dropout_prob=0.05)
    errs, drops = [], []
    sel = np.abs(ANG) < math.radians(5)  # r about 10 m
    for seed in range(40):
        s = scan(w, params=p, seed=seed)
        drops.append(np.isnan(s.ranges).mean())
        ok = sel & np.isfinite(s.ranges)
        errs.append(s.ranges[ok] - s.true_range[ok])
    errs = np.concatenate(errs)
    assert np.mean(drops) == pytest.approx(0.05, abs=0.01)
    assert errs.std() == pytest.approx(0.01 + 0.001 * 10.0, rel=0.1)
    assert abs(errs.mean()) < 0.002


def test_same_seed_same_scan_different_seed_differs():
    w = load_world("office")
    a = scan(w, pose=(10.0, 1.2, 0.3), params=LaserParams(), seed=5)
    b = scan(w, pose=(10.0, 1.2, 0.3), params=LaserParams(), seed=5)
    c = scan(w, pose=(10.0, 1.2, 0.3), params=LaserParams(), seed=6)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    np.testing.assert_array_equal(a.intensities, b.intensities)
    assert not np.array_equal(a.intensities, c.intensities)


def test_intensity_alone_does_not_separate_glass_in_the_office():
    w = load_world("office")
    rng = np.random.default_rng(0)
    I, g, a, r = [], [], [], []
    for x in np.linspace(2, 34, 25):
        s = simulate_scan(w, np.array([x, 1.2, rng.uniform(-0.3, 0.3)]), rng)
        ok = np.isfinite(s.ranges)
        I.append(s.intensities[ok]), g.append(s.is_glass[ok]), a.append(s.incidence[ok]), r.append(s.ranges[ok])
    I, g, a, r = map(np.concatenate, (I, g, a, r))
    assert 0.02 < g.mean() < 0.3

    def bacc(pred):
        return 0.5 * (pred[g].mean() + (~pred[~g]).mean())

    ths = np.percentile(I, np.arange(1, 100))
    best = max(max(bacc(I >= t), bacc(I <= t)) for t in ths)
    assert best < 0.8, best
    # glass returns are confined to small incidence angles, other surfaces are not
    assert np.percentile(a[g], 99) < math.radians(15)
    assert (a[~g] > math.radians(20)).mean() > 0.4
