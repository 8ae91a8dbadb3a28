"""GlassMapper: the per-scan glass path on simulated scans, bad inputs never corrupt the maps, export."""

import math
import pickle

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.mapping import BeamGlass, GlassMapper, MapperConfig, MappingInputError
from glassmap.types import LaserGeometry, Scan


@pytest.fixture(scope="module")
def clf():
    from glassmap.classifier import GlassClassifier

    return GlassClassifier.load_default()


def box_scan(n=1081):
    """A 6 m x 4 m box around a laser at (0.5, 0.3) with yaw 0: ranges and intensities."""
    a = LaserGeometry().angles[:n]
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.stack([np.where(v > 0, v, np.inf) for v in ((3 - 0.5) / c, (-3 - 0.5) / c, (2 - 0.3) / s,
                                                            (-2 - 0.3) / s)])
    r = t.min(axis=0)
    wall = t.argmin(axis=0)
    cos_inc = np.where(wall < 2, np.abs(c), np.abs(s))
    # a diffuse painted wall as the simulator models it: K rho cos(alpha) / r; a multi-echo scan in which
    # every beam had one echo (the default classifier reads echoes)
    return Scan(0.0, r, 6000.0 * 0.65 * cos_inc / np.maximum(r, 0.5), echoes=np.full((n, 1), np.nan),
                echo_intensities=np.zeros((n, 1)))


POSE = np.array([0.5, 0.3, 0.0])


def snapshot(m: GlassMapper):
    return {name: m.grid[name].copy() for name in m.grid.layer_names}, m.grid.origin.copy()


def same(m: GlassMapper, snap) -> bool:
    layers, origin = snap
    return np.array_equal(origin, m.grid.origin) and all(np.array_equal(m.grid[k], v) for k, v in layers.items())


def test_walls_become_not_glass(clf):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    for _ in range(3):
        b = m.process(box_scan(), POSE, 0.05)
    assert isinstance(b, BeamGlass)
    assert b.n_beams == 1081 and b.n_classified > 1000 and b.n_registered == b.n_classified
    assert np.mean(b.p_glass[np.isfinite(b.p_glass)] > 0.5) < 0.02  # diffuse walls
    conf = m.confidence_map()
    occ = np.isfinite(conf)
    assert occ.sum() > 100
    assert np.nanmean(conf) < 0.1
    assert np.isnan(b.p_glass).sum() == np.isnan(b.incidence).sum()
    # the baseline f(i, d, theta) (single-echo input) takes some bright normal-incidence wall beams for glass
    single = box_scan()
    single.echoes = single.echo_intensities = None
    bb, _ = GlassMapper(config=MapperConfig(), classifier=clf).classify(single)
    assert np.mean(bb.p_glass[np.isfinite(bb.p_glass)] > 0.5) < 0.06


def test_simulated_office_glass_and_walls(clf):
    from glassmap.sim.blueprint import Blueprint
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    world = load_world("office")
    bp = Blueprint.from_world(world)
    occ = OccupancyGrid(MapGrid(0.05, origin=tuple(bp.origin), shape=bp.labels.shape))
    m = GlassMapper(occ, MapperConfig(), classifier=clf)
    rng = np.random.default_rng(0)
    wp = world.route()
    for k in range(60):
        xy = wp[0] + (wp[1] - wp[0]) * k / 60
        yaw = math.atan2(*(wp[1] - wp[0])[::-1])
        s = simulate_scan(world, np.array([xy[0], xy[1], yaw]), rng)
        m.process(s.to_scan(), np.array([xy[0], xy[1], yaw]), 0.03)
    h, w = bp.labels.shape
    off = np.rint((bp.origin - m.grid.origin) / 0.05).astype(int)  # the grid grew by whole cells
    lab = m.glass.labels(m.occupancy)[off[1]:off[1] + h, off[0]:off[0] + w]
    glass_cells = (bp.labels == 2) & (lab >= 0)
    wall_cells = (bp.labels == 1) & (lab >= 0)
    assert glass_cells.sum() > 10 and wall_cells.sum() > 100
    assert (lab[glass_cells] == 1).mean() > 0.6
    assert (lab[wall_cells] == 0).mean() > 0.8


def test_direct_and_robust_agree_at_zero_sigma(clf):
    res = []
    for cfg in (MapperConfig(registration="direct"), MapperConfig(registration="robust", window=5)):
        m = GlassMapper(config=cfg, classifier=clf)
        m.process(box_scan(), POSE, 0.0)
        res.append(m.glass.log_odds.copy())
    assert np.allclose(res[0], res[1])


def test_bad_pose_and_sigma_raise_and_change_nothing(clf):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    m.process(box_scan(), POSE, 0.05)
    snap = snapshot(m)
    for pose in (np.array([np.nan, 0, 0]), np.array([0.0, 0.0]), np.array([5e4, 0, 0])):
        with pytest.raises(MappingInputError):
            m.process(box_scan(), pose, 0.05)
    with pytest.raises(MappingInputError, match="per beam"):
        m.process(box_scan(), POSE, np.full(10, 0.05))
    with pytest.raises(MappingInputError):
        m.process(box_scan(), POSE, -1.0)
    assert same(m, snap)
    with pytest.raises(ValueError):  # mismatched intensities are refused by Scan itself
        Scan(0.0, np.ones(5), np.ones(4))


def test_nan_and_empty_scans_are_skipped_and_counted(clf):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    b = m.process(Scan(0.0, np.zeros(0), np.zeros(0)), POSE, 0.05)
    assert b.n_beams == 0 and m.skipped_scans == 1
    snap = snapshot(m)
    b = m.process(Scan(0.0, np.full(1081, np.nan), np.full(1081, 100.0)), POSE, 0.05)
    assert b.n_bad == 1081 and b.n_registered == 0 and np.isnan(b.p_glass).all()
    assert m.skipped_scans == 2
    assert not np.any(m.glass.log_odds) and not np.any(m.occupancy.log_odds)
    sc = box_scan()
    sc.ranges[::10] = np.nan
    sc.intensities[5::10] = np.nan
    sig = np.full(1081, 0.05)
    sig[7::10] = np.nan
    b = m.process(sc, POSE, sig)
    assert b.n_bad == 109 + 108 + 108
    assert np.isnan(b.p_glass[::10]).all() and np.isnan(b.p_glass[5::10]).all()
    assert np.isfinite(m.glass.log_odds).all() and np.isfinite(m.occupancy.log_odds).all()
    assert snap is not None


def test_no_intensities_updates_occupancy_only(clf):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    sc = box_scan()
    b = m.process(Scan(0.0, sc.ranges, None), POSE, 0.05)
    assert b.no_intensities and b.n_classified == 0
    assert m.occupancy.occupied().sum() > 100 and not np.any(m.glass.log_odds)


def test_update_occupancy_false_leaves_the_shared_grid_to_the_caller(clf):
    occ = OccupancyGrid()
    sc = box_scan()
    occ.integrate(POSE, sc.angles, sc.ranges)
    before = occ.log_odds.copy()
    m = GlassMapper(occ, MapperConfig(glass_hits_occupy=False, protect="none"), classifier=clf)
    b = m.process(sc, POSE, 0.05, update_occupancy=False)
    assert np.array_equal(occ.log_odds, before)
    assert b.n_registered > 1000 and np.any(m.glass.log_odds < 0)
    assert m.grid is occ.grid and "glass" in occ.grid.layer_names


def test_register_false_classifies_and_keeps_glass_hits_but_leaves_the_glass_map_alone(clf):
    m = GlassMapper(config=MapperConfig(glass_hit_threshold=0.0), classifier=clf)  # every classified beam a hit
    b = m.process(box_scan(), POSE, None, register=False)
    assert b.n_classified > 1000 and b.n_registered == 0
    assert not np.any(m.glass.log_odds)  # no evidence
    assert m.grid[m.hits_layer].sum() > 100 and m.occupancy.occupied().sum() > 100  # the occupancy side ran
    b = m.process(box_scan(), POSE, 0.05)
    assert b.n_registered == b.n_classified and np.any(m.glass.log_odds)


def test_warm_up_runs_the_glass_hit_path_and_leaves_the_maps_alone(clf, monkeypatch):
    m = GlassMapper(classifier=clf)
    hits = []
    mark = GlassMapper.mark_glass_hits

    def spy(self, *args, **kwargs):
        hits.append(mark(self, *args, **kwargs))
        return hits[-1]

    monkeypatch.setattr(GlassMapper, "mark_glass_hits", spy)
    snap = snapshot(m)
    m.warm_up(box_scan())  # painted walls only: no beam looks like glass
    assert hits and max(hits) > 0  # the glass-hit kernel ran all the same (its first call loads it)
    assert same(m, snap) and m.scans == 0


def test_glass_layer_follows_grid_growth(clf):
    m = GlassMapper(OccupancyGrid(MapGrid(0.05, (-2.0, -2.0), (80, 80), grow_step_m=2.0)), MapperConfig(),
                    classifier=clf)
    m.process(box_scan(), POSE, 0.05)
    m.process(box_scan(), np.array([12.5, 0.3, 0.0]), 0.05)
    assert m.glass.log_odds.shape == m.occupancy.log_odds.shape == m.grid.shape
    assert m.grid.shape[1] > 80


def test_export_writes_png_npy_pgm_yaml(clf, tmp_path):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    m.process(box_scan(), POSE, 0.05)
    paths = m.export(str(tmp_path), "office")
    conf = np.load(paths["npy"])
    assert conf.shape == m.grid.shape and np.isfinite(conf).sum() == m.occupancy.occupied().sum()
    with open(paths["pgm"], "rb") as f:
        assert f.read(2) == b"P5"
    assert "resolution: 0.05" in open(paths["yaml"]).read()
    import matplotlib.image as mpimg

    h, w = mpimg.imread(paths["png"]).shape[:2]
    assert h % 2 == 0 and w % 2 == 0 and 40 < h < 2 * m.grid.shape[0] and 60 < w < 2 * m.grid.shape[1]  # cropped
    full = m.export(str(tmp_path), "full", scale=1, crop=False)
    assert mpimg.imread(full["png"]).shape[:2] == m.grid.shape


def test_config_validation():
    for bad in (dict(registration="nearest"), dict(window=4), dict(decay_ref="x"), dict(aggregation="cell"),
                dict(protect="all"), dict(search_radius=-1)):
        with pytest.raises(ValueError):
            MapperConfig(**bad)


def test_copy_maps_is_an_independent_copy_with_the_same_outputs(clf, tmp_path):
    m = GlassMapper(config=MapperConfig(), classifier=clf)
    m.process(box_scan(), POSE, 0.05)
    copy = m.copy_maps()
    conf = m.confidence_map()
    assert np.array_equal(copy.confidence_map(), conf, equal_nan=True)
    assert np.array_equal(copy.occupancy.probability(), m.occupancy.probability())
    m.process(box_scan(), POSE, 0.05)  # keeps mapping: the copy does not change
    assert np.array_equal(copy.confidence_map(), conf, equal_nan=True)
    assert not np.array_equal(m.confidence_map(), conf, equal_nan=True)
    paths = pickle.loads(pickle.dumps(copy)).export(str(tmp_path))  # picklable: exported by another process
    assert np.array_equal(np.load(paths["npy"]), conf, equal_nan=True)
