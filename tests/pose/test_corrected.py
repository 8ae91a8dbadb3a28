"""Maps rebuilt at corrected poses: the registration sigma is the one relative to the map; glass evidence
carried by the key scans lands on the walls at the corrected poses."""

from dataclasses import replace

import numpy as np
import pytest

from glassmap.mapping import MapperConfig
from glassmap.grid import MapGrid
from glassmap.pose.backend import BackEndConfig, GraphCorrection, corrected_estimate
from glassmap.pose.corrected import MapRebuild, NoClassifier, rebuild_maps, relative_sigma
from glassmap.pose.motion import compose
from glassmap.types import PoseEstimate, Scan
from tests.pose.test_loop_closure import GEOM, _keys, _ring, _route


def test_relative_sigma_is_range_noise_without_pose_error_and_grows_with_yaw():
    k = _keys(_ring(), _route([(-8.5, -4.5), (-7.0, -4.5)]), 0.0)[0]
    r = np.array([1.0, 10.0, np.inf])
    s0 = relative_sigma(replace(k, cov=np.zeros((3, 3))), r)
    np.testing.assert_allclose(s0[:2], [0.011, 0.02])
    assert np.isnan(s0[2])
    s1 = relative_sigma(replace(k, cov=np.diag([0.0, 0.0, 1e-4])), r)
    assert s1[1] > 0.1 > s1[0]  # 10 mrad at 10 m: 10 cm


def test_rebuild_puts_glass_evidence_on_the_walls_at_the_given_poses():
    truth = _route([(-8.5, -4.5), (-5.0, -4.5)])
    keys = [replace(k, scan=Scan(stamp=k.stamp, ranges=k.ranges, intensities=None, geometry=GEOM),
                    p_glass=np.where(np.isfinite(k.ranges), 0.9, np.nan)) for k in _keys(_ring(), truth, 0.0)]
    occ, gm = rebuild_maps(keys, truth, mapper=MapperConfig())  # p(glass) from the key scans: no classification
    conf = gm.confidence_map()
    walls = np.isfinite(conf)
    assert walls.sum() > 200
    assert np.nanmedian(conf[walls]) > 0.6  # glass believed on the walls
    occ_only, none = rebuild_maps(keys, truth)
    assert none is None and (occ_only.occupied() == occ.occupied()).mean() > 0.99


def test_a_rebuild_in_steps_gives_the_maps_of_one_at_once_and_ignores_later_key_scans():
    truth = _route([(-8.5, -4.5), (-5.0, -4.5)])
    keys = [replace(k, scan=Scan(stamp=k.stamp, ranges=k.ranges, intensities=None, geometry=GEOM),
                    p_glass=np.where(np.isfinite(k.ranges), 0.9, np.nan)) for k in _keys(_ring(), truth, 0.0)]
    occ, gm = rebuild_maps(keys, truth, mapper=MapperConfig())
    growing = list(keys[:-5])
    job = MapRebuild(growing, truth, mapper=MapperConfig())
    growing.extend(keys[-5:])  # added after the rebuild started (the worker's graph goes on)
    steps = 1
    while not job.step(7):
        steps += 1
    assert steps == int(np.ceil((len(keys) - 5) / 7)) and job.done
    short, short_gm = rebuild_maps(keys[:-5], truth, mapper=MapperConfig())
    np.testing.assert_array_equal(job.occ.log_odds, short.log_odds)
    np.testing.assert_array_equal(job.glass.confidence_map(), short_gm.confidence_map())
    assert not np.array_equal(job.occ.log_odds, occ.log_odds)


def test_rebuild_on_a_given_grid_keeps_its_origin_and_never_classifies():
    truth = _route([(-8.5, -4.5), (-6.0, -4.5)])
    keys = _keys(_ring(), truth, 0.0)
    occ, _ = rebuild_maps(keys, truth, grid=MapGrid(0.05, origin=(-10.025, -6.025), shape=(40, 60)))
    np.testing.assert_allclose(occ.grid.origin[0] % 0.05, 0.025, atol=1e-9)  # grown on the given lattice
    assert occ.occupied().sum() > 50
    with pytest.raises(RuntimeError, match="p\\(glass\\) from the key scans"):
        NoClassifier().predict_scan(keys[0].scan)


def test_online_sigma_relative_to_the_map_leaves_out_the_maps_own_uncertainty():
    """A robot standing in a room, its map placed 5 cm / 1 deg uncertain relative to the map frame's anchor:
    the "anchor" sigma counts that, the "map" sigma (the pose relative to the map it registers on) does not."""
    from glassmap.pose import EstimatorConfig, PoseEstimator
    from glassmap.pose.corrected import online_sigma
    from glassmap.types import Odometry
    from tests.pose.synth import make_scan, room_with_corner

    est = PoseEstimator(EstimatorConfig(initial_pose=(-1.5, -1.0, 0.0), laser_mount=(0.0, 0.0, 0.0)))
    rng = np.random.default_rng(0)
    for k in range(5):
        est.predict(Odometry(stamp=0.025 * k, x=0.0, y=0.0, yaw=0.0))
        est.update(make_scan(room_with_corner(), np.array([-1.5, -1.0, 0.0]), stamp=0.025 * k, noise=0.01, rng=rng))
    est.chain.cov = np.diag([0.05 ** 2, 0.05 ** 2, np.radians(1.0) ** 2])  # the map's drift so far
    e = est.estimate()
    r = np.array([1.0, 8.0, np.inf])
    anchor, to_map = online_sigma(est, e, r, "anchor"), online_sigma(est, e, r, "map")
    np.testing.assert_array_equal(anchor, est.registration_sigma(e, r))  # the reported covariance's
    assert np.isnan(to_map[2]) and np.isnan(anchor[2])
    assert anchor[0] > 0.05 and anchor[1] > np.radians(1.0) * 8.0  # the map's 5 cm and 1 deg are in it
    assert to_map[0] < 0.04 and to_map[1] < 0.5 * anchor[1]
    with pytest.raises(ValueError, match="map"):
        online_sigma(est, e, r, "world")


def test_corrected_estimate_is_the_graph_node_moved_along_the_front_ends_motion_with_the_nodes_marginal():
    cfg = BackEndConfig()
    est = PoseEstimate(3.0, 1.0, 0.0, 0.1, np.diag([4e-4, 1e-4, 1e-6]), "degraded")
    assert corrected_estimate(est, None, cfg) is est  # no node in the graph yet
    node_cov = np.diag([1e-4, 4e-4, 1e-6])
    corr = GraphCorrection(np.array([1.0, 2.0, np.pi / 2]), front=est.pose.copy(), stamp=3.0, cov=node_cov,
                           closures=2)
    c = corrected_estimate(est, corr, cfg)  # at the node itself: its marginal and the floor, not the front end's
    np.testing.assert_allclose(c.pose, [1.0, 3.0, 0.1 + np.pi / 2], atol=1e-12)  # compose(correction, pose)
    floor = np.diag(np.square(cfg.chain.min_sigma))  # equal in x and y: the same in any frame
    shared = np.diag(np.square(cfg.closure.cov_floor))  # the closures' shared error: once, however many
    np.testing.assert_allclose(c.covariance, node_cov + floor + shared, atol=1e-15)
    before = corrected_estimate(est, replace(corr, closures=0), cfg)  # no closure yet: the chain's marginal
    np.testing.assert_allclose(before.covariance, node_cov + floor, atol=1e-15)
    assert (c.stamp, c.status) == (3.0, "degraded")
    later = replace(est, stamp=4.0, x=2.0)  # 1 m on along the front end's x axis, 1 s later
    moved = corrected_estimate(later, corr, cfg)
    np.testing.assert_allclose(moved.pose[:2], compose(corr.correction, later.pose)[:2], atol=1e-12)
    grow = np.diag(moved.covariance) - np.diag(c.covariance)
    assert np.all(grow > 0)  # odometry noise of the metre, and the node's heading error times the lever arm
    # what the front end's covariance holds beyond its chain (here a lost track's) is added, turned by 90 deg
    lost = corrected_estimate(replace(est, status="lost"), corr, cfg, est.covariance)
    np.testing.assert_allclose(lost.covariance, c.covariance + np.diag([1e-4, 4e-4, 1e-6]), atol=1e-15)
