"""Registration (docs/method.md eq. 6), Bayesian update (eq. 7) with clamping, and direct vs robust assignment
on a hand-made grid, with numbers computed by hand."""

import math

import numpy as np
import pytest

from glassmap.glass import GlassMap, GlassParams
from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.registration import (
    Observations,
    aggregate,
    decayed_probability,
    logit,
    nearest_occupied_cells,
    registration_observations,
    window_offsets,
)


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x)))


def test_eq6_known_numbers():
    # (0.9 - 0.5) * exp(-0.05^2 / (2 * 0.05^2)) + 0.5 = 0.4 * exp(-0.5) + 0.5
    assert decayed_probability(0.9, 0.05, 0.05) == pytest.approx(0.4 * math.exp(-0.5) + 0.5)
    assert decayed_probability(0.9, 0.05, 0.05) == pytest.approx(0.742612, abs=1e-6)
    # distance 0 keeps p; far away -> 0.5; symmetric for p < 0.5
    assert decayed_probability(0.2, 0.0, 0.1) == pytest.approx(0.2)
    assert decayed_probability(0.9, 10.0, 0.05) == pytest.approx(0.5)
    assert decayed_probability(0.1, 0.05, 0.05) == pytest.approx(1.0 - 0.742612, abs=1e-6)
    # sigma 0: only distance 0 receives evidence
    assert decayed_probability(0.9, 0.0, 0.0) == pytest.approx(0.9)
    assert decayed_probability(0.9, 0.05, 0.0) == pytest.approx(0.5)


def test_eq7_bayes_update_in_log_odds_and_clamping():
    g = MapGrid(resolution=0.1, origin=(0.0, 0.0), shape=(4, 4))
    gm = GlassMap(g, GlassParams(l_min=-4.6, l_max=4.6))
    cell = np.array([5])
    gm.update(cell, logit(np.array([0.8])))  # prior 0.5 -> posterior = p = 0.8
    assert gm.probability().ravel()[5] == pytest.approx(0.8, abs=1e-6)
    gm.update(cell, logit(np.array([0.9])))  # 0.8 * 0.9 / (0.8 * 0.9 + 0.2 * 0.1) = 0.72 / 0.74
    assert gm.probability().ravel()[5] == pytest.approx(0.72 / 0.74, abs=1e-6)
    for _ in range(20):
        gm.update(cell, logit(np.array([0.99])))
    assert gm.log_odds.ravel()[5] == pytest.approx(4.6, abs=1e-6)  # clamped, p = 0.990
    assert gm.probability().ravel()[5] == pytest.approx(sigmoid(4.6), abs=1e-6)
    gm.update(cell, logit(np.array([0.1])))  # a clamped cell can still change its mind
    assert gm.log_odds.ravel()[5] == pytest.approx(4.6 - math.log(9.0), abs=1e-5)
    for _ in range(40):
        gm.update(cell, logit(np.array([0.01])))
    assert gm.log_odds.ravel()[5] == pytest.approx(-4.6, abs=1e-6)
    assert np.count_nonzero(gm.log_odds) == 1


def hand_grid():
    """0.1 m cells, origin (0, 0), 10 x 10; only cell (ix 5, iy 5) (centre (0.55, 0.55)) is occupied."""
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(0.0, 0.0), shape=(10, 10)))
    occ.log_odds[5, 5] = 2.0
    return occ


THR = math.log(0.65 / 0.35)


def test_nearest_occupied_cell_and_fallback():
    occ = hand_grid()
    ends = np.array([[0.52, 0.47],   # end-point cell (5, 4) is free; (5, 5) occupied one cell away
                     [0.55, 0.55],   # exactly on the occupied cell
                     [0.15, 0.15]])  # nothing occupied within 2 cells -> its own cell
    cells, found = nearest_occupied_cells(ends, occ.grid.origin, 0.1, occ.log_odds, THR, search_radius=2)
    assert cells.tolist() == [[5, 5], [5, 5], [1, 1]]
    assert found.tolist() == [True, True, False]
    # a second occupied cell nearer to the first end point wins
    occ.log_odds[4, 4] = 2.0  # centre (0.45, 0.45): distance 0.073 < 0.085
    cells, _ = nearest_occupied_cells(ends[:1], occ.grid.origin, 0.1, occ.log_odds, THR, search_radius=2)
    assert cells.tolist() == [[4, 4]]


def test_direct_vs_robust_assignment_on_hand_grid():
    occ = hand_grid()
    end = np.array([[0.52, 0.47]])
    cells, _ = nearest_occupied_cells(end, occ.grid.origin, 0.1, occ.log_odds, THR)
    shape = occ.grid.shape

    direct = registration_observations(np.array([0.9]), end, cells, 0.1, occ.grid.origin, 0.1, shape, "direct")
    assert direct.flat.tolist() == [5 * 10 + 5]
    assert sigmoid(direct.log_odds) == pytest.approx([0.9])

    robust = registration_observations(np.array([0.9]), end, cells, 0.1, occ.grid.origin, 0.1, shape,
                                       "robust", k=3, decay_ref="cell")
    got = dict(zip(robust.flat.tolist(), sigmoid(robust.log_odds).tolist()))
    assert len(got) == 9
    assert got[55] == pytest.approx(0.9)  # c_hat gets p itself
    side = 0.4 * math.exp(-0.01 / 0.02) + 0.5  # 0.1 m away: 0.742612
    diag = 0.4 * math.exp(-0.02 / 0.02) + 0.5  # 0.1414 m away: 0.647152
    for c in (54, 56, 45, 65):
        assert got[c] == pytest.approx(side)
    for c in (44, 46, 64, 66):
        assert got[c] == pytest.approx(diag)

    ep = registration_observations(np.array([0.9]), end, cells, 0.1, occ.grid.origin, 0.1, shape,
                                   "robust", k=3, decay_ref="endpoint")
    got = dict(zip(ep.flat.tolist(), sigmoid(ep.log_odds).tolist()))
    d2 = 0.03 ** 2 + 0.08 ** 2  # end point (0.52, 0.47) to centre (0.55, 0.55)
    assert got[55] == pytest.approx(0.4 * math.exp(-d2 / 0.02) + 0.5)  # 0.777678 < 0.9

    five = registration_observations(np.array([0.9]), end, cells, 0.1, occ.grid.origin, 0.1, shape, "robust", k=5)
    assert len(five.flat) == 25
    corner = dict(zip(five.flat.tolist(), sigmoid(five.log_odds).tolist()))[33]  # (3, 3): 0.2828 m away
    assert corner == pytest.approx(0.4 * math.exp(-0.08 / 0.02) + 0.5)


def test_robust_observations_are_eq6_of_each_window_cell():
    """Every (beam, window cell) observation of the cell-referenced robust method is exactly the logit of
    eq. 6 at that cell's distance, with per-beam sigmas (zero included)."""
    rng = np.random.default_rng(5)
    n, res, k = 200, 0.05, 5
    p = rng.uniform(0.01, 0.99, n)
    sigma = rng.uniform(0.0, 0.2, n)
    sigma[:10] = 0.0
    cells = np.stack([rng.integers(5, 95, n), rng.integers(5, 95, n)], axis=1)
    obs = registration_observations(p, np.zeros((n, 2)), cells, sigma, np.zeros(2), res, (100, 100), "robust", k=k)
    offs = window_offsets(k)
    dist = np.hypot(offs[:, 0], offs[:, 1]) * res
    want = logit(np.clip(decayed_probability(p[:, None], dist[None, :], sigma[:, None]), 1e-3, 1 - 1e-3))
    flat = (cells[:, 1] * 100 + cells[:, 0])[:, None] + (offs[:, 1] * 100 + offs[:, 0])[None, :]
    keep = want != 0.0
    np.testing.assert_array_equal(obs.flat, flat[keep])
    np.testing.assert_array_equal(obs.log_odds, want[keep])


def test_window_cells_outside_grid_are_dropped():
    occ = hand_grid()
    cells = np.array([[0, 0]])
    obs = registration_observations(np.array([0.9]), np.array([[0.05, 0.05]]), cells, 0.1, occ.grid.origin, 0.1,
                                    occ.grid.shape, "robust", k=3)
    assert sorted(obs.flat.tolist()) == [0, 1, 10, 11]


def test_per_scan_aggregation_mean_vs_per_beam_sum():
    obs = Observations(np.array([7, 7, 3]), logit(np.array([0.9, 0.6, 0.2])))
    cells, scan = aggregate(obs, "scan")
    assert cells.tolist() == [3, 7]
    assert scan == pytest.approx([logit(0.2), (logit(0.9) + logit(0.6)) / 2])
    cells, beam = aggregate(obs, "beam")
    assert beam == pytest.approx([logit(0.2), logit(0.9) + logit(0.6)])
    # sparse indices take the sort path and agree
    far = Observations(np.array([10_000_000, 5, 5]), np.array([1.0, 2.0, 4.0]))
    cells, mean = aggregate(far, "scan")
    assert cells.tolist() == [5, 10_000_000] and mean.tolist() == [3.0, 1.0]
    with pytest.raises(ValueError):
        aggregate(obs, "cell")


def test_aggregation_of_cells_spread_over_a_wide_map_equals_np_unique():
    """Cells spread over many rows of a wide grid (the sorting path): the cells in increasing order and,
    bit for bit, the sums and means np.unique + bincount give."""
    rng = np.random.default_rng(3)
    width = 5000
    ix, iy = rng.integers(100, 160, 4000), rng.integers(10, 90, 4000)
    obs = Observations(iy * width + ix, rng.normal(0.0, 2.0, 4000))
    uniq, inv, count = np.unique(obs.flat, return_inverse=True, return_counts=True)
    total = np.bincount(inv, weights=obs.log_odds)
    cells, beam = aggregate(obs, "beam")
    np.testing.assert_array_equal(cells, uniq)
    np.testing.assert_array_equal(beam, total)
    cells, scan = aggregate(obs, "scan")
    np.testing.assert_array_equal(scan, total / count)


def test_window_offsets_validation():
    assert window_offsets(3).shape == (9, 2)
    assert [0, 0] in window_offsets(5).tolist()
    with pytest.raises(ValueError):
        window_offsets(4)
