"""The likelihood field's compiled passes equal the numpy / scipy code they replaced, bit for bit: the coarse
maximum, the cells near a wall and their nearest occupied cells (the exact distance transform's), the distinct
nearest cells, the neighbourhood sums of the end-point layers, the bilinear wall vectors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from glassmap.pose.field_jit import forward_maximum, near_cells, neighbour_sums, unique_cells, wall_vectors


@pytest.mark.parametrize("shape, f", [((60, 45), 4), ((7, 5), 4), ((3, 2), 5), ((1, 1), 4), ((20, 30), 1),
                                      ((20, 30), 2), ((40, 33), 3)])
def test_forward_maximum_equals_scipy_maximum_filter(shape, f):
    rng = np.random.default_rng(f * 1000 + shape[0])
    a = rng.normal(size=shape).astype(np.float32)
    a[rng.random(shape) < 0.6] = np.float32(np.log(0.01))  # the floor, many ties
    want = ndimage.maximum_filter(a, size=f, origin=-(f // 2), mode="nearest")
    assert forward_maximum(a, f).tobytes() == want.tobytes()


@pytest.mark.parametrize("shape, cut_c, density", [((50, 70), 5, 0.03), ((9, 4), 2, 0.03), ((1, 1), 1, 0.03),
                                                   ((30, 30), 0, 0.03), ((40, 60), 4, 0.3), ((25, 31), 3, 0.6),
                                                   ((64, 64), 4, 0.005)])
def test_near_cells_and_unique_cells_equal_the_distance_transform_selection(shape, cut_c, density):
    """The cells within the cut of a wall and their nearest occupied cells are scipy's exact distance
    transform's, ties (many at these densities) broken the same way."""
    rng = np.random.default_rng(cut_c * 100 + shape[0])
    occ = rng.random(shape) < density
    occ[0, 0] = True
    ny, nx = ndimage.distance_transform_edt(~occ, return_distances=False, return_indices=True)
    ddy = ny - np.arange(shape[0], dtype=ny.dtype)[:, None]
    ddx = nx - np.arange(shape[1], dtype=nx.dtype)[None, :]
    near = np.nonzero(ddx * ddx + ddy * ddy <= cut_c * cut_c)
    got = near_cells(occ, cut_c * cut_c)
    for g, want in zip(got, (*near, ny[near], nx[near], ddy[near], ddx[near])):
        assert g.dtype == want.dtype and g.tobytes() == want.tobytes()
    u, inv = np.unique(ny[near].astype(np.int64) * shape[1] + nx[near], return_inverse=True)
    gu, ginv = unique_cells(got[2], got[3], *shape)
    assert gu.tobytes() == u.tobytes() and np.array_equal(ginv, inv)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 24), st.integers(1, 24), st.floats(0.0, 0.7), st.integers(0, 6), st.integers(0, 2 ** 32 - 1))
def test_near_cells_take_the_distance_transforms_nearest_cell_whatever_the_grid(h, w, density, cut_c, seed):
    """Any grid, any cut: the same cells near a wall and the same nearest occupied cell for each."""
    occ = np.random.default_rng(seed).random((h, w)) < density
    if not occ.any():
        occ[h // 2, w // 2] = True
    ny, nx = ndimage.distance_transform_edt(~occ, return_distances=False, return_indices=True)
    iy, ix, gy, gx, _, _ = near_cells(occ, cut_c * cut_c)
    assert np.array_equal(gy, ny[iy, ix]) and np.array_equal(gx, nx[iy, ix])
    d2 = (ny - np.arange(h)[:, None]) ** 2 + (nx - np.arange(w)[None, :]) ** 2
    assert np.array_equal(np.flatnonzero(d2.ravel() <= cut_c * cut_c), iy * w + ix)


@pytest.mark.parametrize("r", [1, 2])
def test_neighbour_sums_equal_the_numpy_gather(r):
    rng = np.random.default_rng(r)
    h, w, res = 23, 31, 0.05
    cnt = rng.integers(0, 5, (h, w)).astype(np.float32)
    sx, sy = (cnt * rng.random((h, w)).astype(np.float32) * np.float32(res) for _ in range(2))
    cy = np.r_[0, h - 1, rng.integers(0, h, 40)].astype(np.int64)  # corners: neighbours off the grid
    cx = np.r_[w - 1, 0, rng.integers(0, w, 40)].astype(np.int64)
    d = np.arange(-r, r + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
    yy, xx = cy[:, None] + dy[None, :], cx[:, None] + dx[None, :]
    inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    yy, xx = np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)
    c = np.where(inside, cnt[yy, xx], 0).astype(np.float64)
    ax = np.where(inside, sx[yy, xx], 0) + c * (dx * res)[None, :]
    ay = np.where(inside, sy[yy, xx], 0) + c * (dy * res)[None, :]
    for g, want in zip(neighbour_sums(sx, sy, cnt, cy, cx, r, res), (c, ax, ay)):
        assert g.tobytes() == want.tobytes()


def _numpy_wall_vectors(vx, vy, xy, origin, res, w, h):
    """LikelihoodField.wall_vectors' numpy code before the kernel."""
    out = np.full(xy.shape, np.nan)
    g = (xy - origin) / res - 0.5
    x0, y0 = np.floor(g[:, 0]), np.floor(g[:, 1])
    with np.errstate(invalid="ignore"):  # inf - inf on the point off at infinity
        ax, ay = g[:, 0] - x0, g[:, 1] - y0
        inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    base = np.where(inside, y0 * w + x0, 0).astype(np.int64)
    corners = ((0, (1 - ax) * (1 - ay)), (1, ax * (1 - ay)), (w, (1 - ax) * ay), (w + 1, ax * ay))
    ivx = sum(c * vx[base + d] for d, c in corners)
    ivy = sum(c * vy[base + d] for d, c in corners)
    out[inside] = np.stack([ivx, ivy], axis=1)[inside]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_wall_vectors_equal_the_numpy_interpolation(seed):
    rng = np.random.default_rng(seed)
    h, w, res = int(rng.integers(2, 40)), int(rng.integers(2, 40)), float(rng.choice([0.05, 0.1, 0.025]))
    vx = rng.normal(0, 0.05, h * w).astype(np.float32)
    vy = rng.normal(0, 0.05, h * w).astype(np.float32)
    vx[rng.random(h * w) < 0.3] = np.float32(10.0)  # far
    vy[rng.random(h * w) < 0.3] = np.float32(-0.0)
    origin = rng.normal(0, 3, 2)
    xy = origin + rng.uniform(-0.2, 1.2, (500, 2)) * np.array([w, h]) * res  # some off the field
    xy[:20] = origin + (rng.integers(0, max(w, h), (20, 2)) + 0.5) * res  # on cell centres
    xy[20] = np.nan
    xy[21, 0] = np.inf
    got = wall_vectors(vx, vy, xy, float(origin[0]), float(origin[1]), res, w, h)
    assert got.tobytes() == _numpy_wall_vectors(vx, vy, xy, origin, res, w, h).tobytes()
