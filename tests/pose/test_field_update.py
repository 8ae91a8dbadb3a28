"""Likelihood field brought up to date with the grid (``LikelihoodField.update``): only the cells that can have
changed are computed again, and the field is the one a rebuild of the same crop gives, to the last bit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.pose.field import FieldParams, LikelihoodField

RES = 0.05


def _grid(rng: np.random.Generator, shape: tuple[int, int], density: float
          ) -> tuple[OccupancyGrid, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A grid with straight walls and scattered occupied cells, each occupied cell holding 1-4 end points."""
    grid = MapGrid(resolution=RES, origin=(-1.0, -2.0), shape=shape)
    occ = OccupancyGrid(grid)
    occupied = rng.random(shape) < density
    occupied[shape[0] // 3, 5:-5] = True  # a wall along x
    occupied[5:-5, shape[1] // 2] = True  # and one along y
    layers = tuple(np.zeros(shape, np.float32) for _ in range(3))
    _add_points(rng, layers, np.nonzero(occupied))
    occ.log_odds[occupied] = 2.0
    return occ, layers


def _add_points(rng: np.random.Generator, layers, cells) -> None:
    iy, ix = cells
    n = rng.integers(1, 5, size=iy.size).astype(np.float32)
    layers[0][iy, ix] += n * rng.uniform(0, RES, iy.size).astype(np.float32)
    layers[1][iy, ix] += n * rng.uniform(0, RES, iy.size).astype(np.float32)
    layers[2][iy, ix] += n


def _assert_same(a, b) -> None:
    for name in ("fine", "coarse", "vx", "vy", "nearest", "counts"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.n_occupied == b.n_occupied and a.shape == b.shape


def _change(rng: np.random.Generator, occ: OccupancyGrid, layers, n_flip: int, n_hit: int) -> None:
    """Clear and occupy ``n_flip`` cells each, and add end points to ``n_hit`` cells (occupied or not)."""
    shape = occ.log_odds.shape
    on = np.argwhere(occ.log_odds > 0.6)
    clear = on[rng.choice(len(on), size=min(n_flip, len(on)), replace=False)]
    occ.log_odds[clear[:, 0], clear[:, 1]] = -1.0
    add = (rng.integers(0, shape[0], n_flip), rng.integers(0, shape[1], n_flip))
    occ.log_odds[add] = 2.0
    _add_points(rng, layers, add)
    _add_points(rng, layers, (rng.integers(0, shape[0], n_hit), rng.integers(0, shape[1], n_hit)))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), density=st.sampled_from([0.002, 0.02, 0.1]),
       n_flip=st.integers(0, 30), n_hit=st.integers(0, 60), with_points=st.booleans(),
       params=st.sampled_from([FieldParams(half_size=2.0, pad=16), FieldParams(half_size=2.0, pad=16, pool=2),
                               FieldParams(half_size=2.0, pad=16, line_normals=False, pool=0),
                               FieldParams(half_size=2.0, pad=16, vectors=False)]))
def test_update_gives_the_field_a_rebuild_of_the_crop_gives(seed, density, n_flip, n_hit, with_points, params):
    rng = np.random.default_rng(seed)
    occ, layers = _grid(rng, (90, 110), density)
    fld = LikelihoodField(params)
    centre = np.array([1.6, 0.1])
    first = fld.compute(fld.snapshot(occ, centre, layers if with_points else None))
    for _ in range(2):  # twice: the second update starts from arrays an update wrote
        _change(rng, occ, layers, n_flip, n_hit)
        inputs = fld.snapshot(occ, centre, layers if with_points else None)
        first = fld.update(first, inputs)
        _assert_same(first, fld.compute(inputs))


def test_refresh_keeps_the_crop_and_falls_back_to_a_rebuild_when_it_differs():
    rng = np.random.default_rng(3)
    occ, layers = _grid(rng, (90, 110), 0.02)
    fld = LikelihoodField(FieldParams(half_size=2.0, pad=16))
    fld.refresh(occ, layers)  # nothing installed yet: a rebuild around the field's centre
    assert fld.ready
    fld.rebuild(occ, np.array([1.6, 0.1]), layers)
    origin = fld.origin.copy()
    _change(rng, occ, layers, 10, 40)
    fld.refresh(occ, layers)
    np.testing.assert_array_equal(fld.origin, origin)
    again = LikelihoodField(FieldParams(half_size=2.0, pad=16))
    again.rebuild(occ, np.array([1.6, 0.1]), layers)
    _assert_same(fld.arrays, again.arrays)
    # another crop (the update is given the snapshot of another centre): the whole field is computed
    moved = fld.snapshot(occ, np.array([0.4, -0.5]), layers)
    _assert_same(fld.update(fld.arrays, moved), fld.compute(moved))


@pytest.mark.parametrize("n_flip,n_hit", [(0, 0), (0, 5)])
def test_an_update_without_new_occupied_cells_keeps_every_nearest_cell(n_flip, n_hit):
    rng = np.random.default_rng(5)
    occ, layers = _grid(rng, (60, 60), 0.02)
    fld = LikelihoodField(FieldParams(half_size=2.0, pad=16))
    first = fld.compute(fld.snapshot(occ, np.zeros(2), layers))
    nearest = first.nearest.copy()
    _change(rng, occ, layers, n_flip, n_hit)
    _assert_same(fld.update(first, fld.snapshot(occ, np.zeros(2), layers)),
                 fld.compute(fld.snapshot(occ, np.zeros(2), layers)))
    np.testing.assert_array_equal(first.nearest, nearest)
