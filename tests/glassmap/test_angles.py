"""Incidence angles from line segments: known geometry gives known angles, corners keep their own wall's
angle, beams on no line get none, bad input is refused."""

import math
from pathlib import Path

import numpy as np
import pytest

from glassmap.angles import METHODS, incidence_angles, split_merge
from glassmap.types import LaserGeometry


def box_scan(px=0.5, py=0.3, xw=3.0, yw=2.0, noise=0.0, seed=0):
    """Ranges and true incidence angles of a laser at (px, py), yaw 0, inside the box |x| < xw, |y| < yw."""
    a = LaserGeometry().angles
    c, s = np.cos(a), np.sin(a)
    ts = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, pos in (("x", xw), ("x", -xw), ("y", yw), ("y", -yw)):
            t = (pos - px) / c if axis == "x" else (pos - py) / s
            ts.append(np.where(t > 0, t, np.inf))
    t = np.stack(ts)
    r = t.min(axis=0)
    wall = t.argmin(axis=0)
    normal = np.array([[1, 0], [1, 0], [0, 1], [0, 1]])[wall]
    true = np.arccos(np.abs(c * normal[:, 0] + s * normal[:, 1]))
    r = r + np.random.default_rng(seed).normal(0, noise, r.shape)
    return a, r, true, wall, px + r * c, py + r * s


@pytest.mark.parametrize("method", METHODS)
def test_box_gives_known_angles(method):
    a, r, true, _, _, _ = box_scan(noise=0.005)
    res = incidence_angles(a, r, method)
    ok = np.isfinite(res.incidence)
    assert ok.mean() > 0.97
    err = np.degrees(np.abs(res.incidence[ok] - true[ok]))
    assert np.median(err) < 0.3
    assert np.percentile(err, 99) < 1.0
    assert res.n_segments >= 3
    assert ((res.segment >= 0) == ok).all()


@pytest.mark.parametrize("method", METHODS)
def test_points_near_a_corner_keep_their_own_wall(method):
    a, r, true, wall, x, y = box_scan(noise=0.003)
    res = incidence_angles(a, r, method)
    corner = np.array([3.0, 2.0])
    d = np.hypot(x - corner[0], y - corner[1])
    near = (d > 0.08) & (d < 0.6) & np.isfinite(res.incidence)
    assert near.sum() > 20
    err = np.degrees(np.abs(res.incidence[near] - true[near]))
    assert err.max() < 2.0  # the neighbouring wall would give an error of tens of degrees


def test_far_walls_on_the_same_infinite_line_do_not_share_a_segment():
    # two collinear pieces of wall x = 3 separated by a 1.5 m opening (the beams there see nothing)
    a, r, true, wall, x, y = box_scan(noise=0.003)
    gap = (wall == 0) & (np.abs(y) < 0.75)
    r = np.where(gap, np.inf, r)
    for method in METHODS:
        res = incidence_angles(a, r, method)
        up = (wall == 0) & (y > 0.75) & (res.segment >= 0)
        down = (wall == 0) & (y < -0.75) & (res.segment >= 0)
        assert up.any() and down.any()
        assert set(res.segment[up]).isdisjoint(set(res.segment[down]))


@pytest.mark.parametrize("method", METHODS)
def test_scattered_points_get_no_angle(method):
    rng = np.random.default_rng(3)
    a = LaserGeometry().angles
    r = rng.uniform(1.0, 8.0, a.shape)  # clutter: no three neighbours on a line
    res = incidence_angles(a, r, method)
    assert np.isfinite(res.incidence).mean() < 0.05


@pytest.mark.parametrize("method", METHODS)
def test_invalid_ranges_get_no_angle_and_empty_scan_is_fine(method):
    a, r, _, _, _, _ = box_scan()
    r[::7] = np.nan
    r[100:200] = np.inf
    res = incidence_angles(a, r, method)
    assert np.isnan(res.incidence[::7]).all() and np.isnan(res.incidence[100:200]).all()
    assert np.isfinite(res.incidence).mean() > 0.7
    empty = incidence_angles(np.zeros(0), np.zeros(0), method)
    assert empty.incidence.shape == (0,) and empty.n_segments == 0
    allnan = incidence_angles(a, np.full(a.shape, np.nan), method)
    assert np.isnan(allnan.incidence).all()


def test_bad_input_is_refused():
    with pytest.raises(ValueError):
        incidence_angles(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="unknown angle method"):
        incidence_angles(np.zeros(3), np.zeros(3), "ransac")


def test_normal_incidence_is_zero():
    # a wall straight ahead at x = 2: the centre beam hits it at 0 rad, beam at angle b at |b|
    a = LaserGeometry().angles
    with np.errstate(divide="ignore"):
        r = np.where(np.abs(a) < math.radians(40), 2.0 / np.cos(a), np.nan)
    res = incidence_angles(a, r)
    mid = np.argmin(np.abs(a))
    assert res.incidence[mid] == pytest.approx(0.0, abs=math.radians(0.1))
    k = np.flatnonzero(np.isfinite(res.incidence))
    assert np.allclose(res.incidence[k], np.abs(a[k]), atol=math.radians(0.05))


def test_glass_fragments_between_pass_through_beams_get_their_panes_angle():
    # a pane along y = 1 returns only every other beam or so near normal incidence; the other beams pass
    # through and hit a wall along y = 2: both lines get their own, correct angles
    a = LaserGeometry().angles
    rng = np.random.default_rng(5)
    look = (a > math.radians(60)) & (a < math.radians(120))
    pane = look & (rng.uniform(size=a.size) < 0.5)
    with np.errstate(divide="ignore"):
        r = np.where(pane, 1.0 / np.sin(a), 2.0 / np.sin(a))
    r = np.where(look, r + rng.normal(0, 0.005, a.size), np.nan)
    true = np.abs(a - np.pi / 2)
    for method in METHODS:
        res = incidence_angles(a, r, method)
        for sel in (pane, look & ~pane):
            ok = sel & np.isfinite(res.incidence)
            assert ok.sum() > 0.8 * sel.sum(), method
            assert np.median(np.degrees(np.abs(res.incidence[ok] - true[ok]))) < 0.5
        assert set(res.segment[pane & (res.segment >= 0)]).isdisjoint(res.segment[look & ~pane & (res.segment >= 0)])


def test_split_merge_matches_the_reference_on_recorded_scans():
    """13 scans of a simulated office run (deskewed beam angles, glass and mirror returns) and the segments
    and incidence angles split-merge gave for them before its speed-ups (issue 19): the same segments, and
    the same angles within 1e-9 rad. (The normals now come from half-angle formulas instead of numpy's
    arctan2 / sin / cos, a few ulps apart; arccos amplifies that near normal incidence to ~5e-13 rad.)"""
    ref = np.load(Path(__file__).parent / "data" / "split_merge_reference.npz")
    for a, r, seg, inc in zip(ref["beam_angles"], ref["ranges"], ref["segment"], ref["incidence"]):
        res = split_merge(a, r)
        np.testing.assert_array_equal(res.segment, seg)
        np.testing.assert_array_equal(np.isnan(res.incidence), np.isnan(inc))
        ok = ~np.isnan(inc)
        np.testing.assert_allclose(res.incidence[ok], inc[ok], rtol=0, atol=1e-9)


def test_split_merge_angles_are_numpys_arccos_of_the_clipped_cosines_to_the_bit():
    """Each beam's incidence is np.arccos(np.clip(|u . n|, 0, 1)) of its beam direction u (np.cos, np.sin) and
    its segment's normal n, as when the kernel returned the cosines and the caller clipped and scattered them."""
    ref = np.load(Path(__file__).parent / "data" / "split_merge_reference.npz")
    for a, r in zip(ref["beam_angles"], ref["ranges"]):
        res = split_merge(a, r)
        on = res.segment >= 0
        nrm = res.normals[res.segment[on]]
        cos = np.abs(np.cos(a[on]) * nrm[:, 0] + np.sin(a[on]) * nrm[:, 1])
        np.testing.assert_array_equal(res.incidence[on], np.arccos(np.clip(cos, 0.0, 1.0)))
        assert np.isnan(res.incidence[~on]).all() and on.any()


def test_distance_stand_in_compares_with_the_threshold_as_hypot():
    """angles_jit._distance_for (breakpoints and the second pass's links) gives ``>`` and ``<=`` against the
    threshold the results of the C library's hypot (numba's math.hypot, np.hypot; not CPython's math.hypot),
    also at and around the threshold and for NaN, inf, 0 and tiny values."""
    from glassmap.angles_jit import _distance_for

    rng = np.random.default_rng(9)
    dx, dy = rng.normal(size=20000) * 0.1, rng.normal(size=20000) * 0.1
    h = np.hypot(dx, dy)
    thr = np.concatenate([h[:5000], np.nextafter(h[5000:10000], np.inf), np.nextafter(h[10000:15000], 0.0),
                          rng.uniform(0.0, 0.3, 5000)])
    cases = list(zip(dx, dy, thr)) + [(a, b, t) for a in (0.0, -0.0, 1e-160, 3.0, np.nan, np.inf)
                                      for b in (0.0, 2e-200, -4.0, np.nan)
                                      for t in (0.0, -1.0, 1e-150, 1e-140, 5.0, 1e200, np.inf, np.nan)]
    for a, b, t in cases:
        d, ref = _distance_for(a, b, t), np.hypot(a, b)
        assert (d > t) == (ref > t) and (d <= t) == (ref <= t), (a, b, t)
