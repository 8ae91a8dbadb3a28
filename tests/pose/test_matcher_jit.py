"""The matcher's compiled lookups (glassmap/pose/matcher_jit.py) give the scores of the numpy code they
replaced to the last bit: coarse cell lookups, the bilinear wall-vector interpolation, one origin or one
per yaw, points off the crop (clamped into its border); the wall-vector kernel's square lattices of
translations."""

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.pose.field import LikelihoodField
from glassmap.pose.matcher import CorrelativeMatcher, MatcherConfig, select_points
from tests.pose.synth import make_scan, room_with_corner


def numpy_scores(field_arr, fld, pts, w, xy0, yaws, tx, ty, margin, bilinear=False):
    """``CorrelativeMatcher._scores`` before the kernels (issue 19e), for the coarse and the wall-vector paths."""
    res = fld.resolution
    h, wd = fld.shape
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    xy0 = np.asarray(xy0, dtype=np.float64).reshape(-1, 2)
    fx = (c * pts[:, 0] - s * pts[:, 1] + (xy0[:, :1] - fld.origin[0])) / res
    fy = (s * pts[:, 0] + c * pts[:, 1] + (xy0[:, 1:] - fld.origin[1])) / res
    off = ty.astype(np.int64) * wd + tx.astype(np.int64)
    wf = w.astype(np.float32)
    if not bilinear:
        ix = np.clip(np.floor(fx).astype(np.int64), margin, wd - 1 - margin)
        iy = np.clip(np.floor(fy).astype(np.int64), margin, h - 1 - margin)
        base = iy * wd + ix
        return field_arr[base[:, None, :] + off[None, :, None]] @ wf
    gx, gy = fx - 0.5, fy - 0.5
    x0, y0 = np.floor(gx), np.floor(gy)
    ax, ay = (gx - x0).astype(np.float32), (gy - y0).astype(np.float32)
    ix = np.clip(x0.astype(np.int64), margin, wd - 2 - margin)
    iy = np.clip(y0.astype(np.int64), margin, h - 2 - margin)
    base = (iy * wd + ix)[:, None, :] + off[None, :, None]
    corners = ((0, (1 - ax) * (1 - ay)), (1, ax * (1 - ay)), (wd, (1 - ax) * ay), (wd + 1, ax * ay))
    vx = np.zeros(base.shape, dtype=np.float32)
    vy = np.zeros(base.shape, dtype=np.float32)
    for dflat, coef in corners:
        b = base + dflat
        vx += fld.vx[b] * coef[:, None, :]
        vy += fld.vy[b] * coef[:, None, :]
    d2 = vx * vx + vy * vy
    d2 *= np.float32(-0.5 / fld.params.sigma_hit ** 2)
    return np.log(np.exp(d2) + np.float32(fld.params.p_floor)) @ wf


@pytest.fixture(scope="module")
def room():
    segs = room_with_corner()
    occ = OccupancyGrid(MapGrid())
    for i in range(3):
        pose = np.array([0.03 * i, -0.02 * i, np.radians(0.7) * i])
        s = make_scan(segs, pose, noise=0.01, rng=np.random.default_rng(100 + i))
        occ.integrate(pose, s.angles, s.ranges)
    fld = LikelihoodField()
    fld.rebuild(occ, np.zeros(2))
    s = make_scan(segs, np.array([0.1, -0.05, 0.02]), noise=0.01, rng=np.random.default_rng(7))
    pts, w, _ = select_points(s.angles, s.ranges, np.zeros(3), MatcherConfig())
    return fld, pts, w


def test_scores_equal_the_numpy_lookups_to_the_bit(room):
    fld, pts, w = room
    m = CorrelativeMatcher()
    rng = np.random.default_rng(3)
    margin = fld.params.pad // 2
    for trial in range(12):
        k = int(rng.integers(1, 9))
        p = pts + rng.normal(0.0, 0.02, pts.shape)
        if trial % 3 == 2:  # some points far off the crop: clamped into its border
            p[::7] *= 40.0
        wt = w * rng.uniform(0.2, 1.0, w.shape)
        yaws = rng.uniform(-0.2, 0.2) + np.arange(k) * 0.003
        tx, ty = rng.integers(-12, 13, 25), rng.integers(-12, 13, 25)
        side = int(rng.integers(1, 10))  # the wall-vector path scores a square lattice of translations
        lx, ly = np.meshgrid(np.arange(side) + rng.integers(-12, 13 - side),
                             np.arange(side) + rng.integers(-12, 13 - side))
        xy0 = rng.normal(0.0, 0.3, (k, 2)) if trial % 2 else rng.normal(0.0, 0.3, 2)
        for arr, bilinear in ((fld.coarse, False), (fld.fine, False), (fld.fine, True)):
            if bilinear:
                tx, ty = lx.ravel(), ly.ravel()
            got = m._scores(arr, fld, p, wt, xy0, yaws, tx, ty, margin, bilinear)
            want = numpy_scores(arr, fld, p, wt, xy0, yaws, tx, ty, margin, bilinear)
            assert got.dtype == want.dtype == np.float32
            np.testing.assert_array_equal(got, want)


def test_a_match_is_unchanged_by_the_kernels(room, monkeypatch):
    """The whole match (lattice peak, covariance, information) with the numpy lookups swapped back in."""
    fld, pts, w = room
    m = CorrelativeMatcher()
    prior = np.diag([0.1 ** 2, 0.1 ** 2, np.radians(2.0) ** 2])
    got = m.match(fld, pts, w, np.array([0.05, 0.0, 0.0]), prior)
    monkeypatch.setattr(CorrelativeMatcher, "_scores", lambda self, *a: numpy_scores(*a))
    want = m.match(fld, pts, w, np.array([0.05, 0.0, 0.0]), prior)
    assert got is not None and want is not None
    for name in ("pose", "covariance", "peak_pose", "information"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert (got.quality, got.n_poses, got.edge) == (want.quality, want.n_poses, want.edge)


def test_the_wall_vector_kernel_takes_only_a_square_lattice_inside_the_field(room):
    fld, pts, w = room
    m = CorrelativeMatcher()
    margin = fld.params.pad // 2
    lx, ly = (g.ravel() for g in np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)))
    m._scores(fld.fine, fld, pts, w, np.zeros(2), np.zeros(2), lx, ly, margin, True)
    for tx, ty in ((lx[::-1], ly[::-1]), (lx[:-1], ly[:-1]), (np.array([0, 3]), np.array([0, 0]))):
        with pytest.raises(ValueError, match="square lattice"):
            m._scores(fld.fine, fld, pts, w, np.zeros(2), np.zeros(2), tx, ty, margin, True)
    with pytest.raises(ValueError, match="past the field"):
        m._scores(fld.fine, fld, pts, w, np.zeros(2), np.zeros(2), lx, ly + fld.shape[0], margin, True)
