"""The likelihood field's compiled passes equal the numpy / scipy code they replaced, bit for bit: the coarse
maximum, the cells near a wall, the distinct nearest cells, the neighbourhood sums of the end-point layers."""

import numpy as np
import pytest
from scipy import ndimage

from glassmap.pose.field_jit import forward_maximum, near_cells, neighbour_sums, unique_cells


@pytest.mark.parametrize("shape, f", [((60, 45), 4), ((7, 5), 4), ((3, 2), 5), ((1, 1), 4), ((20, 30), 1),
                                      ((20, 30), 2), ((40, 33), 3)])
def test_forward_maximum_equals_scipy_maximum_filter(shape, f):
    rng = np.random.default_rng(f * 1000 + shape[0])
    a = rng.normal(size=shape).astype(np.float32)
    a[rng.random(shape) < 0.6] = np.float32(np.log(0.01))  # the floor, many ties
    want = ndimage.maximum_filter(a, size=f, origin=-(f // 2), mode="nearest")
    assert forward_maximum(a, f).tobytes() == want.tobytes()


def nearest_occupied(rng, shape):
    occ = rng.random(shape) < 0.03
    occ[0, 0] = True
    return ndimage.distance_transform_edt(~occ, return_distances=False, return_indices=True)


@pytest.mark.parametrize("shape, cut_c", [((50, 70), 5), ((9, 4), 2), ((1, 1), 1), ((30, 30), 0)])
def test_near_cells_and_unique_cells_equal_the_numpy_selection(shape, cut_c):
    ny, nx = nearest_occupied(np.random.default_rng(cut_c), shape)
    ddy = ny - np.arange(shape[0], dtype=ny.dtype)[:, None]
    ddx = nx - np.arange(shape[1], dtype=nx.dtype)[None, :]
    near = np.nonzero(ddx * ddx + ddy * ddy <= cut_c * cut_c)
    got = near_cells(ny, nx, cut_c * cut_c)
    for g, want in zip(got, (*near, ny[near], nx[near], ddy[near], ddx[near])):
        assert g.dtype == want.dtype and g.tobytes() == want.tobytes()
    u, inv = np.unique(ny[near].astype(np.int64) * shape[1] + nx[near], return_inverse=True)
    gu, ginv = unique_cells(got[2], got[3], *shape)
    assert gu.tobytes() == u.tobytes() and np.array_equal(ginv, inv)


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
