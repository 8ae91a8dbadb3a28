"""Occupancy grid: known geometry gives known cells; growth keeps layers aligned; bad input is refused."""

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid, OccupancyParams, hit_margins


def test_world_cell_round_trip():
    g = MapGrid(resolution=0.05, origin=(-1.0, -2.0), shape=(10, 10))
    cells = g.world_to_cell(np.array([[-1.0, -2.0], [-0.951, -1.951], [-0.949, -2.0]]))
    assert cells.tolist() == [[0, 0], [0, 0], [1, 0]]
    assert np.allclose(g.cell_to_world(np.array([1, 0])), [-0.925, -1.975])


def test_growth_pads_all_layers_and_keeps_world_positions():
    g = MapGrid(resolution=0.1, origin=(0.0, 0.0), shape=(10, 10), grow_step_m=1.0)
    g.add_layer("a", fill=0.0)
    g.add_layer("b", fill=0.5)
    g.add_layer("c", fill=np.nan, dtype=np.float64)
    g.add_layer("d", fill=False, dtype=bool)
    g["a"][g.world_to_cell(np.array([0.55, 0.25]))[::-1].tolist()[0], 5] = 7.0
    g["b"][:] = np.arange(100, dtype=np.float32).reshape(10, 10)
    g["d"][3, 4] = True
    assert g.ensure_contains(np.array([-0.5, -0.05]), np.array([0.5, 0.5]))
    assert g.shape == (20, 20) and g["b"].shape == (20, 20)
    assert np.allclose(g.origin, [-1.0, -1.0])
    ix, iy = g.world_to_cell(np.array([0.55, 0.25]))
    assert g["a"][iy, ix] == 7.0 and g["b"][0, 0] == 0.5
    old = (slice(10, 20), slice(10, 20))  # the old cells, 1 m (10 cells) in from the new corner
    assert np.array_equal(g["b"][old], np.arange(100, dtype=np.float32).reshape(10, 10))
    new = np.ones((20, 20), bool)
    new[old] = False
    assert (g["a"][new] == 0).all() and (g["b"][new] == 0.5).all() and np.isnan(g["c"]).all()
    assert [g[k].dtype for k in "abcd"] == [np.float32, np.float32, np.float64, bool]
    assert g["d"].sum() == 1 and g["d"][13, 14]
    assert not g.ensure_contains(np.array([0.0, 0.0]), np.array([0.5, 0.5]))


def test_single_beam_marks_free_then_occupied():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 40)))
    assert occ.params.hit_margin == pytest.approx(0.2)
    occ.integrate(np.array([0.0, 0.0, 0.0]), np.array([0.0]), np.array([2.0]))
    lo = occ.log_odds
    row = occ.grid.world_to_cell(np.array([0.0, 0.0]))[1]
    end_ix = occ.grid.world_to_cell(np.array([2.0, 0.0]))[0]
    assert lo[row, end_ix] == pytest.approx(0.85)
    start_ix = occ.grid.world_to_cell(np.array([0.0, 0.0]))[0]
    assert np.allclose(lo[row, start_ix:end_ix - 2], -0.4)  # cleared up to 0.2 m short of the end point
    assert (lo[row, end_ix - 2:end_ix] == 0).all()
    assert (lo[row + 1] == 0).all()  # nothing off the beam
    assert occ.occupied().sum() == 1


def test_a_beam_clears_at_least_up_to_one_cell_short_of_its_end_point():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 40)), OccupancyParams(hit_margin=0.0))
    occ.integrate(np.array([0.0, 0.0, 0.0]), np.array([0.0]), np.array([2.0]))
    row = occ.grid.world_to_cell(np.array([0.0, 0.0]))[1]
    end_ix = occ.grid.world_to_cell(np.array([2.0, 0.0]))[0]
    assert occ.log_odds[row, end_ix - 2] == pytest.approx(-0.4) and occ.log_odds[row, end_ix - 1] == 0


def _share_of_wall_points_in_occupied_cells(params: OccupancyParams, wall_y: float) -> float:
    """A robot drives 4 m along x at y = 0 past a wall at y = wall_y, seen at 5-85 deg, range noise 1.5 cm."""
    rng = np.random.default_rng(0)
    occ = OccupancyGrid(MapGrid(resolution=0.05, origin=(-1.0, -1.0), shape=(60, 300)), params)
    angles = np.radians(np.linspace(5.0, 85.0, 400))
    points = []
    for x in np.arange(0.0, 4.0, 0.05):
        r = wall_y / np.sin(angles) + rng.normal(0.0, 0.015, angles.size)
        occ.integrate(np.array([x, 0.0, 0.0]), angles, r)
        points.append(np.stack([x + r * np.cos(angles), r * np.sin(angles)], axis=1))
    ix, iy = occ.grid.world_to_cell(np.concatenate(points)).T
    return float(occ.occupied()[iy, ix].mean())


def test_the_hit_margin_keeps_the_near_side_of_a_wall_seen_obliquely():
    # clearing up to one cell short of each end point, the beams that measured long erase cells holding the end
    # points of the beams that measured short (the wall's near side); the margin keeps them
    walls = (1.0, 1.01, 1.02, 1.03, 1.04)  # the wall at several offsets within a cell
    one_cell = OccupancyParams(hit_margin=0.05, surface_margin=0.05)
    lost_one_cell = np.mean([1 - _share_of_wall_points_in_occupied_cells(one_cell, y) for y in walls])
    lost_default = np.mean([1 - _share_of_wall_points_in_occupied_cells(OccupancyParams(), y) for y in walls])
    assert lost_one_cell > 0.03
    assert lost_default < 0.5 * lost_one_cell


def test_beams_inside_a_continuous_surface_get_the_surface_margin_and_its_edges_the_long_one():
    angles = np.radians(np.arange(-20.0, 20.0, 0.25))  # 160 beams at the UTM-30LX's spacing
    ranges = 2.0 / np.cos(angles)  # a wall 2 m ahead: neighbours 3 beams apart lie 5 cm apart
    ranges[80:] += 1.5  # a range jump: the wall steps back 1.5 m from beam 80 on
    ranges[120] = np.nan  # a beam without a return: the beams 3 either side lose one of their neighbours
    hit = np.isfinite(ranges)
    c, s = np.cos(angles), np.sin(angles)
    m = hit_margins(c, s, ranges, hit, edge=0.2, surface=0.1)
    edge = np.flatnonzero(m == 0.2)
    assert set(edge) == {0, 1, 2, 77, 78, 79, 80, 81, 82, 117, 123, 157, 158, 159}
    assert np.all(np.delete(m, edge) == 0.1)
    assert np.all(hit_margins(c, s, ranges, hit, edge=0.2, surface=0.2) == 0.2)


def test_no_return_clears_only_when_configured_and_nan_is_ignored():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-5.0, -5.0), shape=(100, 100)))
    assert occ.integrate(np.zeros(3), np.array([0.0, 1.0]), np.array([np.inf, np.nan])) == 0
    assert (occ.log_odds == 0).all()
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-5.0, -5.0), shape=(100, 100)),
                        OccupancyParams(no_return_range=3.0))
    occ.integrate(np.zeros(3), np.array([0.0, 1.0]), np.array([np.inf, np.nan]))
    assert (occ.log_odds > 0).sum() == 0 and (occ.log_odds < 0).sum() == 30


def test_protect_mask_keeps_cells_from_being_cleared():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 40)))
    occ.grid.ensure_contains(np.array([-2.0, -2.0]), np.array([4.0, 2.0]))
    protect = np.zeros(occ.grid.shape, bool)
    ix, iy = occ.grid.world_to_cell(np.array([1.0, 0.0]))
    protect[iy, ix] = True
    occ.integrate(np.zeros(3), np.array([0.0]), np.array([2.0]), protect=protect)
    assert occ.log_odds[iy, ix] == 0 and occ.log_odds[iy, ix - 1] < 0


def test_bad_inputs():
    occ = OccupancyGrid()
    with pytest.raises(ValueError, match="shape"):
        occ.integrate(np.zeros(3), np.zeros(3), np.ones(4))
    with pytest.raises(ValueError, match="laser_pose"):
        occ.integrate(np.array([np.nan, 0, 0]), np.zeros(1), np.ones(1))
    assert occ.integrate(np.zeros(3), np.zeros(0), np.zeros(0)) == 0


def test_pgm_yaml_export(tmp_path):
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 40)))
    for _ in range(3):  # one observation (p = 0.40) is not yet "free" (threshold 0.35)
        occ.integrate(np.zeros(3), np.array([0.0]), np.array([2.0]))
    pgm, yaml = occ.save_pgm_yaml(str(tmp_path / "map"))
    h, w = occ.grid.shape
    header = b"P5\n%d %d\n255\n" % (w, h)
    data = open(pgm, "rb").read()
    assert data.startswith(header) and len(data) == len(header) + h * w
    img = np.frombuffer(data[len(header):], np.uint8).reshape(h, w)
    assert (img == 0).sum() == 1 and (img == 254).sum() >= 10
    ox, oy = occ.grid.origin
    assert "resolution: 0.1" in open(yaml).read() and f"origin: [{ox:.4f}, {oy:.4f}, 0.0]" in open(yaml).read()


def test_protect_callable_is_evaluated_after_growth_and_bad_shape_is_refused():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 20), grow_step_m=1.0))
    seen = []

    def mask():
        seen.append(occ.grid.shape)
        return np.zeros(occ.grid.shape, bool)

    occ.integrate(np.zeros(3), np.array([0.0]), np.array([5.0]), protect=mask)
    assert seen == [occ.grid.shape] and occ.grid.shape != (20, 20)
    with pytest.raises(ValueError, match="protect mask shape"):
        occ.integrate(np.zeros(3), np.array([0.0]), np.array([1.0]), protect=np.zeros((3, 3), bool))


def test_each_cell_is_updated_once_per_scan():
    occ = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 40)))
    angles = np.full(50, 0.0)  # fifty identical beams: one observation, not fifty
    occ.integrate(np.zeros(3), angles, np.full(50, 2.0))
    assert occ.log_odds.max() == pytest.approx(0.85) and occ.log_odds.min() == pytest.approx(-0.4)


def test_ensure_scan_extent_grows_like_integrate():
    a = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 20), grow_step_m=1.0))
    b = OccupancyGrid(MapGrid(resolution=0.1, origin=(-1.0, -1.0), shape=(20, 20), grow_step_m=1.0))
    angles, ranges = np.array([0.0, 2.0]), np.array([6.0, 3.0])
    assert a.ensure_scan_extent(np.zeros(3), angles, ranges)
    b.integrate(np.zeros(3), angles, ranges)
    assert a.grid.shape == b.grid.shape and np.allclose(a.grid.origin, b.grid.origin)
    assert (a.log_odds == 0).all()  # growing writes nothing
    assert not a.ensure_scan_extent(np.zeros(3), angles, ranges)


def test_copy_holds_the_chosen_layers_and_does_not_follow_changes():
    g = MapGrid(resolution=0.1, origin=(0.0, 0.0), shape=(10, 10), grow_step_m=1.0)
    g.add_layer("a", fill=0.0)
    g.add_layer("b", fill=0.5)
    c = g.copy(["a"])
    assert c.layer_names == ["a"] and c.shape == g.shape and np.array_equal(c.origin, g.origin)
    g["a"][0, 0] = 3.0
    g.ensure_contains(np.array([-0.5, 0.0]), np.array([0.5, 0.5]))
    assert c["a"][0, 0] == 0.0 and c.shape == (10, 10) and np.allclose(c.origin, [0.0, 0.0])
    assert c.ensure_contains(np.array([-0.5, 0.0]), np.array([0.5, 0.5]))  # a copy grows on its own
    with pytest.raises(ValueError, match="no layer"):
        g.copy(["nope"])


def test_ensure_contains_grows_exactly_when_a_corner_leaves_the_grid():
    """The box's corner cells decide, on each side: a corner in the first / last cell needs no growth, one
    just past it grows that side only; non-finite corners are refused."""
    g = MapGrid(resolution=0.1, origin=(0.0, 0.0), shape=(10, 20), grow_step_m=0.5)
    eps = 1e-9
    assert not g.ensure_contains(np.array([0.0, 0.0]), np.array([2.0 - eps, 1.0 - eps]))
    assert (g.shape, g.generation) == ((10, 20), 0)
    for lo, hi, shape, origin in (([-eps, 0.0], [1.0, 0.5], (10, 25), (-0.5, 0.0)),
                                  ([0.0, 0.0], [1.0, 1.0], (15, 25), (-0.5, 0.0)),
                                  ([0.0, -0.01], [2.0, 0.5], (20, 30), (-0.5, -0.5))):
        assert g.ensure_contains(np.array(lo), np.array(hi))
        assert g.shape == shape and np.allclose(g.origin, origin)
    with pytest.raises(ValueError, match="finite"):
        g.ensure_contains(np.array([np.nan, 0.0]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="finite"):
        g.ensure_contains(np.array([0.0, 0.0]), np.array([1.0, np.inf]))
