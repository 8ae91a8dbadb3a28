"""The one-pass registration update (GlassMap.update_evidence, glassmap/registration_jit.py::update_windows)
gives the glass map of the numpy path it replaced (registration_observations, aggregate, GlassMap.update) to
the last bit: direct and robust registration, both decay references, both aggregations, window cells off
the grid, many beams on one cell, values clamped at the limits; and the mapper over simulated scans gives the
maps of the numpy registration and glass hits (GlassMapper.mark_glass_hits, grid_jit.raise_end_cells)."""

import math

import numpy as np
import pytest

from glassmap.glass import GlassMap, GlassParams
from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.mapping import GlassMapper, MapperConfig, end_points
from glassmap.registration import aggregate, nearest_occupied_cells, registration_observations, window_evidence

SETTINGS = [("direct", 3, "cell"), ("robust", 3, "cell"), ("robust", 5, "cell"), ("robust", 3, "endpoint"),
            ("robust", 7, "endpoint")]


def numpy_update(glass: GlassMap, p, ends, cells, sigma, method, k, decay_ref, aggregation) -> None:
    """The glass-map update of ``GlassMapper.register`` before the one-pass kernel (issue 19)."""
    g = glass.grid
    obs = registration_observations(p, ends, cells, sigma, g.origin, g.resolution, g.shape, method=method, k=k,
                                    decay_ref=decay_ref, p_clip=glass.params.p_clip)
    glass.update(*aggregate(obs, aggregation))


@pytest.mark.parametrize("aggregation", ["scan", "beam"])
@pytest.mark.parametrize("method,k,decay_ref", SETTINGS)
def test_update_evidence_equals_the_numpy_path_to_the_bit(method, k, decay_ref, aggregation):
    rng = np.random.default_rng(7)
    params = GlassParams(l_min=-2.3, l_max=3.1)
    maps = [GlassMap(MapGrid(0.05, (-1.0, -0.5), (40, 60)), params) for _ in range(2)]
    start = rng.normal(0.0, 1.0, maps[0].log_odds.shape).astype(np.float32)
    for gm in maps:
        gm.log_odds[...] = start
    for _ in range(12):
        n = int(rng.integers(0, 400))
        # beams bunched on a few cells (many observations per cell) and spread up to and past the edges
        cells = np.stack([rng.integers(-3, 63, n), rng.integers(-3, 43, n)], axis=1)
        cells[: n // 3] = cells[: n // 3] % 4 + 20
        ends = maps[0].grid.cell_to_world(cells) + rng.uniform(-0.025, 0.025, (n, 2))
        p = rng.uniform(0.0, 1.0, n)
        p[::7] = 0.5  # log-odds 0: dropped by the robust method, kept (in the mean) by the direct one
        p[1::11] = rng.choice([0.0, 1.0], p[1::11].shape)  # clipped to p_clip
        sigma = rng.uniform(0.0, 0.15, n)
        sigma[::5] = 0.0
        numpy_update(maps[0], p, ends, cells, sigma, method, k, decay_ref, aggregation)
        g = maps[1].grid
        ev = window_evidence(p, ends, cells, sigma, g.origin, g.resolution, method, k, decay_ref, params.p_clip)
        maps[1].update_evidence(ev, aggregation)
        np.testing.assert_array_equal(maps[1].log_odds, maps[0].log_odds)
        assert maps[1].updates == maps[0].updates
    lo = maps[1].log_odds
    assert (lo == np.float32(params.l_min)).any() and (lo == np.float32(params.l_max)).any()  # limits reached
    assert maps[1].updates > 0 and not np.array_equal(lo, start)


def test_update_evidence_refuses_an_unknown_aggregation():
    gm = GlassMap(MapGrid(0.05, (0.0, 0.0), (10, 10)))
    ev = window_evidence(np.array([0.9]), np.zeros((1, 2)), np.array([[3, 3]]), 0.05, gm.grid.origin, 0.05)
    with pytest.raises(ValueError):
        gm.update_evidence(ev, "cell")


class ReferenceMapper(GlassMapper):
    """``GlassMapper`` with the registration and the glass hits of before the compiled passes (issue 19)."""

    def mark_glass_hits(self, beams, use, scan, laser_pose, *, ends=None) -> int:
        glass = beams.p_glass[use] > self.config.glass_hit_threshold
        n_sel = int(np.count_nonzero(glass))
        if not n_sel:
            return 0
        ex, ey = end_points(laser_pose, scan.angles, scan.ranges, use) if ends is None else ends
        x, y = ex[glass], ey[glass]
        g = self.grid
        g.ensure_contains(np.array([x.min() - 1.0, y.min() - 1.0]), np.array([x.max() + 1.0, y.max() + 1.0]))
        cells = g.world_to_cell(np.stack([x, y], axis=1))
        flat = cells[:, 1] * g.shape[1] + cells[:, 0]
        lo = self.occupancy.log_odds.reshape(-1)
        if self.config.glass_hits_occupy:
            lo[flat] = np.maximum(lo[flat], np.float32(self.occupancy.params.l_occ))
        if self.config.protect == "hits":
            self.grid[self.hits_layer].reshape(-1)[flat] = True
        return n_sel

    def register(self, beams, use, scan, laser_pose, sigma, *, ends=None) -> int:
        n_use = int(np.count_nonzero(use))
        if not n_use:
            return 0
        cfg, g = self.config, self.grid
        ex, ey = end_points(laser_pose, scan.angles, scan.ranges, use) if ends is None else ends
        margin = (cfg.window // 2 + cfg.search_radius + 2) * g.resolution
        g.ensure_contains(np.array([ex.min() - margin, ey.min() - margin]),
                          np.array([ex.max() + margin, ey.max() + margin]))
        xy = np.stack([ex, ey], axis=1)
        cells, _ = nearest_occupied_cells(xy, g.origin, g.resolution, self.occupancy.log_odds, self._occ_thr,
                                          cfg.search_radius)
        numpy_update(self.glass, beams.p_glass[use], xy, cells, sigma[use], cfg.registration, cfg.window,
                     cfg.decay_ref, cfg.aggregation)
        return n_use


@pytest.mark.parametrize("config", [MapperConfig(), MapperConfig(registration="direct", aggregation="beam"),
                                    MapperConfig(window=5, decay_ref="endpoint", glass_hits_occupy=False),
                                    MapperConfig(protect="glass", glass_hit_threshold=0.3)])
def test_mapper_on_simulated_office_scans_equals_the_numpy_path(config):
    from glassmap.classifier import GlassClassifier
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    clf = GlassClassifier.load_default()
    world = load_world("office")
    mappers = [cls(OccupancyGrid(MapGrid(0.05, (-2.0, -2.0), (80, 80), grow_step_m=2.0)), config, classifier=clf)
               for cls in (ReferenceMapper, GlassMapper)]
    rng = np.random.default_rng(3)
    wp = world.route()
    yaw = math.atan2(*(wp[1] - wp[0])[::-1])
    for k in range(25):
        pose = np.array([*(wp[0] + (wp[1] - wp[0]) * k / 25), yaw])
        scan = simulate_scan(world, pose, rng).to_scan()
        sigma = rng.uniform(0.0, 0.08, scan.ranges.shape)  # per beam, as the runtime's online sigma
        noisy = pose + rng.normal(0.0, [0.03, 0.03, 0.01])  # registered at an estimate, occupancy at the truth
        out = [m.process(scan, noisy, sigma, update_occupancy=k % 3 == 0, occupancy_pose=pose) for m in mappers]
        np.testing.assert_array_equal(out[1].p_glass, out[0].p_glass)
        assert out[1].n_registered == out[0].n_registered > 0
    ref, new = (m.grid for m in mappers)
    np.testing.assert_array_equal(new.origin, ref.origin)
    assert new.layer_names == ref.layer_names
    for name in ref.layer_names:
        np.testing.assert_array_equal(new[name], ref[name])
    assert np.any(new["glass"] > 0) and np.any(new["glass"] < 0)
    if config.protect == "hits":
        assert new["glass_hits"].any()


def _one_wall_beam(returns, neighbour_log_odds):
    """A wall beam (p = 0.02) registered on cell (5, 5) with sigma 5 cm (a neighbour's decay weight 0.61), the
    cell to its right holding ``neighbour_log_odds`` before the update; returns the map after it."""
    from dataclasses import replace

    gm = GlassMap(MapGrid(0.05, (0.0, 0.0), (10, 10)), GlassParams())
    gm.log_odds[5, 6] = neighbour_log_odds
    g = gm.grid
    ev = window_evidence(np.array([0.02]), np.array([[0.275, 0.275]]), np.array([[5, 5]]), np.array([0.05]),
                         g.origin, g.resolution, "robust", 3, "cell", 1e-3)
    gm.update_evidence(ev if returns is None else replace(ev, returns=np.array([returns])), "beam")
    return gm.log_odds


def test_visibility_spares_a_believed_pane_from_an_oblique_wall_beam():
    """A wall seen at 40 deg next to a cell the map believes is glass (p 0.88): a pane would not have returned
    that beam, so the neighbour keeps most of its belief; a neighbour believed wall, the centre cell and a beam
    at normal incidence (a pane would return it) are updated as by eq. 6."""
    oblique = math.exp(-math.radians(40.0) ** 2 / (2 * math.radians(10.0) ** 2))
    plain, vis = _one_wall_beam(None, 2.0), _one_wall_beam(oblique, 2.0)
    q = 1 / (1 + math.exp(-2.0))
    w = math.exp(-0.5)  # a side neighbour 5 cm away at sigma 5 cm
    p_plain = (0.02 - 0.5) * w + 0.5
    p_vis = (0.02 - 0.5) * w * ((1 - q) + q * oblique) + 0.5
    assert plain[5, 6] == pytest.approx(2.0 + math.log(p_plain / (1 - p_plain)), abs=1e-5)  # about 2 - 1.34
    assert vis[5, 6] == pytest.approx(2.0 + math.log(p_vis / (1 - p_vis)), abs=1e-5)  # about 2 - 0.14
    assert vis[5, 5] == plain[5, 5] < -3.0  # the centre gets p(g_j) either way
    wall_plain, wall_vis = _one_wall_beam(None, -2.0), _one_wall_beam(oblique, -2.0)
    assert wall_vis[5, 6] - -2.0 < 0.8 * (wall_plain[5, 6] - -2.0) < 0.0  # most of eq. 6's evidence
    np.testing.assert_array_equal(_one_wall_beam(1.0, 2.0), plain)  # normal incidence: a pane returns it


def test_visibility_without_incidence_angles_registers_as_eq_6():
    """Beams without an incidence angle (e.g. key scans stored without it) get eq. 6's evidence, never NaN."""
    from glassmap.classifier import GlassClassifier
    from glassmap.mapping import BeamGlass
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    world = load_world("office")
    wp = world.route()
    pose = np.array([*wp[0], math.atan2(*(wp[1] - wp[0])[::-1])])
    scan = simulate_scan(world, pose, np.random.default_rng(1)).to_scan()
    maps = []
    for cfg in (MapperConfig(visibility=True), MapperConfig()):
        m = GlassMapper(OccupancyGrid(MapGrid(0.05, (-2.0, -2.0), (80, 80))), cfg,
                        classifier=GlassClassifier.load_default())
        m.glass.log_odds[...] = 1.0  # every cell believed glass: visibility would matter everywhere
        beams, use = m.classify(scan)
        m.integrate(scan, pose)
        no_angle = BeamGlass(beams.p_glass, np.full_like(beams.incidence, np.nan))
        assert m.register(no_angle, use, scan, pose, np.full(scan.ranges.shape, 0.03)) > 0
        maps.append(m.glass.log_odds)
    assert np.all(np.isfinite(maps[0]))
    np.testing.assert_array_equal(maps[0], maps[1])
