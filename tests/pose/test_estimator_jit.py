"""The compiled per-beam loops of the pose estimator give the numpy code they replaced bit for bit."""

import numpy as np

from glassmap.grid import MapGrid
from glassmap.pose.estimator_jit import add_hits, mean_keys, registration_sigmas


def _end_points(rng, n):
    """End points around a 2 m x 1.5 m grid: most inside, some off it, several per cell, some on cell edges."""
    end = rng.uniform([-2.3, -1.8], [2.3, 1.8], size=(n, 2))
    q = n // 4
    end[:q] = end[q: 2 * q]  # repeated points
    end[n // 2: n // 2 + 20] = np.round(end[n // 2: n // 2 + 20] / 0.05) * 0.05  # on cell edges
    return end


def _grid(rng):
    g = MapGrid(0.05, (-1.0, -0.75), (30, 40))  # 2 m x 1.5 m
    lay = rng.uniform(0.0, 1e-3, g.shape).astype(np.float32)
    lay[rng.random(g.shape) < 0.3] = np.inf
    lay[0, :5] = np.nan
    return g, lay


def test_registration_sigmas_equal_the_numpy_sigmas():
    rng = np.random.default_rng(1)
    r_in = rng.uniform(0.0, 30.0, 2000)
    r_in[::7], r_in[::11], r_in[::13], r_in[5] = np.inf, np.nan, -np.inf, 0.0
    for sxy2, sth2, rs, rspm in ((1e-4, 3e-6, 0.01, 0.001), (0.0, 0.0, 0.0, 0.0), (2.5, 0.1, 0.03, 0.0)):
        r = np.where(np.isfinite(r_in), r_in, 0.0)
        sr = rs + rspm * r
        want = np.where(np.isfinite(r_in), np.sqrt(sxy2 + r * r * sth2 + sr * sr), np.nan)
        assert registration_sigmas(r_in, sxy2, sth2, rs, rspm).tobytes() == want.tobytes()


def test_add_hits_equals_add_at():
    rng = np.random.default_rng(2)
    for trial in range(20):
        g, _ = _grid(rng)
        end = _end_points(rng, int(rng.integers(1, 400)))
        init = [rng.uniform(-1, 1, g.shape).astype(np.float32) for _ in range(4)]
        key_value = np.float32(rng.integers(0, 5000))
        cells = g.world_to_cell(end)
        ok = g.in_bounds(cells)
        cells, xy = cells[ok], end[ok]
        off = xy - (g.origin + cells * g.resolution)
        flat = cells[:, 1] * g.shape[1] + cells[:, 0]
        want = [a.copy() for a in init]
        for lay, vals in zip(want, (off[:, 0], off[:, 1], np.ones(len(flat)))):
            np.add.at(lay.reshape(-1), flat, vals.astype(np.float32))
        np.add.at(want[3], (cells[:, 1], cells[:, 0]), key_value)  # the estimator's key layer, as it was added
        got = [a.copy() for a in init]
        key = got[3] if trial % 4 else np.zeros((0, 0), np.float32)  # without a key layer
        add_hits(*got[:3], key, key_value, end, float(g.origin[0]), float(g.origin[1]), float(g.resolution))
        if not trial % 4:
            want[3] = init[3]
        for a, b in zip(got, want):
            assert a.tobytes() == b.tobytes()


def test_mean_keys_equal_the_numpy_anchors():
    rng = np.random.default_rng(3)
    for _ in range(20):
        g, _ = _grid(rng)
        xy = _end_points(rng, int(rng.integers(1, 400)))
        count = rng.integers(0, 4, g.shape).astype(np.float32)
        key = (count * rng.uniform(0, 3000, g.shape)).astype(np.float32)
        c = g.world_to_cell(xy)  # the estimator's numpy code
        c = c[g.in_bounds(c)]
        ix, iy = c[:, 0], c[:, 1]
        n = count[iy, ix]
        on = n > 0
        want = np.floor(key[iy[on], ix[on]] / n[on] + 0.5).astype(np.int32)
        got = mean_keys(key, count, xy, float(g.origin[0]), float(g.origin[1]), float(g.resolution))
        assert got.dtype == np.int32 and got.tobytes() == want.tobytes()
