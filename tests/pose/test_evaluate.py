"""glassmap pose eval's stress options: odometry reaching the estimator late, scans dropped at random."""

import numpy as np
import pytest

from glassmap.pose.evaluate import axis_nees, metrics, run_estimator
from glassmap.sim.dataset import simulate_run
from glassmap.sim.world import load_world

ROUTE = np.array([[10.0, 1.2], [14.0, 1.2]])  # 4 m along the office's glass facade


def test_late_odometry_and_dropped_scans_keep_the_track_and_the_covariance_honest():
    run = simulate_run(load_world("office"), ROUTE, seed=3)
    traj, est = run_estimator(run, odometry_lag=0.4, drop_scans=0.5)
    assert 0.4 * run.n_scans < len(traj.stamps) < 0.6 * run.n_scans  # the trajectory holds the scans kept
    assert np.all(np.diff(traj.stamps) > 0)
    m = metrics(traj, run)
    assert est.stats.lost_events == 0 and m.lost_events == 0
    assert m.gated == 0 and m.inside_95 > 0.85  # the scans ahead of the odometry are held, not diverged


def test_online_glass_map_registers_with_the_runtimes_sigma(monkeypatch):
    """--glass-weighting online builds the glass map as the runtime does by default: the registration sigma is
    the pose's uncertainty relative to the map built so far (mapping.registration_sigma = map)."""
    import glassmap.pose.corrected as corrected
    from runtime.config import MappingConfig

    sources = []
    real = corrected.online_sigma

    def spy(estimator, estimate, ranges, source="map"):
        sources.append(source)
        return real(estimator, estimate, ranges, source)

    monkeypatch.setattr(corrected, "online_sigma", spy)
    run = simulate_run(load_world("office"), ROUTE, seed=3)
    traj, est = run_estimator(run, glass_online=True)
    assert len(sources) == len(traj.stamps)
    assert set(sources) == {MappingConfig().registration_sigma}
    assert np.nanmax(est.occupancy.grid["glass"]) > 0.5  # the facade's glass was mapped


def test_a_run_with_the_pose_graph_reports_its_figures():
    """With a back end the metrics carry the loop-closure columns (no loop on 4 m: no closure, the chain
    left scaled, the optimised poses those of the front end)."""
    from glassmap.pose.backend import GraphBackEnd

    run = simulate_run(load_world("office"), ROUTE, seed=3)
    traj, _ = run_estimator(run, backend=GraphBackEnd())
    m = metrics(traj, run).as_dict()
    assert m["lc_closures"] == 0 and m["lc_false_closures"] == 0 and m["lc_chain_unscaled"] == 0
    assert m["lc_checks"] >= 0 and np.isfinite(m["lc_opt_ate_rmse"])
    assert abs(m["lc_opt_ate_rmse"] - m["ate_rmse"]) < 1e-3
    # the corrected estimate's covariance is the graph's: the chain of key scans compounded from the start
    assert traj.corrected_covs.shape == traj.covs.shape and m["lc_nees_mean"] > 0.0 and 0.0 < m["lc_inside_95"] <= 1.0
    xy = traj.corrected_covs[:, 0, 0] + traj.corrected_covs[:, 1, 1]
    assert xy[-1] > 2.0 * xy[len(xy) // 10]  # a random walk without a closure: it grows along the route


def test_the_mean_nees_splits_into_key_scans_and_the_scans_between_them():
    """The run's mean NEES is the key-share-weighted mean of its two parts; a key scan's error is measured
    against the chain's covariance at it, the other scans' against that plus the odometry since it."""
    run = simulate_run(load_world("office"), ROUTE, seed=3)
    traj, _ = run_estimator(run)
    m = metrics(traj, run)
    k = traj.key.mean()
    assert 0.0 < k < 1.0
    assert m.nees_mean == pytest.approx(k * m.nees_key_mean + (1.0 - k) * m.nees_between_mean)
    assert 0.0 < m.yaw_nees_key_mean < m.nees_key_mean and 0.0 < m.yaw_nees_between_mean < m.nees_between_mean
    # each axis alone: 1 dof each, and with the heading's own variance the same as the split's
    assert m.yaw_nees_mean == pytest.approx(k * m.yaw_nees_key_mean + (1.0 - k) * m.yaw_nees_between_mean)
    assert m.along_nees_mean > 0.0 and m.cross_nees_mean > 0.0
    # the key scans' covariance is the smaller: no odometry since the key scan
    assert np.median(traj.covs[traj.key, 2, 2]) < np.median(traj.covs[~traj.key, 2, 2])


def test_each_axis_alone_is_measured_along_and_across_the_true_heading():
    """Heading 90 deg: x is across the track, y along it. Errors (along 2 cm, across 1 cm, yaw 0.01 rad)
    under variances along 4e-4, across 1e-4 and a correlated x-y part: the marginal variance of each axis."""
    err = np.array([[-0.01, 0.02, 0.01]])  # map frame (x, y, yaw)
    cov = np.array([[[1e-4, 5e-5, 0.0], [5e-5, 4e-4, 0.0], [0.0, 0.0, 2.5e-4]]])
    out = axis_nees(err, cov, np.array([np.pi / 2]))[0]
    # along = (0, 1): error 0.02, variance 4e-4 -> 1.0; across = (-1, 0): error 0.01, variance 1e-4 -> 1.0
    assert out == pytest.approx([1.0, 1.0, 0.4])
    # heading 0: along is x (error -0.01 over 1e-4 -> 1.0), across is y (0.02 over 4e-4 -> 1.0)
    assert axis_nees(err, cov, np.array([0.0]))[0] == pytest.approx([1.0, 1.0, 0.4])
    # a 3-dof NEES (here the sum: no correlation) near its band can hide axes that compensate: position 10x
    # too wide, heading 1.2x too narrow
    wide = np.array([[[1e-3, 0.0, 0.0], [0.0, 4e-3, 0.0], [0.0, 0.0, 2.5e-4 / 3.0]]])
    nees = axis_nees(err, wide, np.array([0.0]))[0]
    assert nees == pytest.approx([0.1, 0.1, 1.2]) and 1.0 < nees.sum() < 1.5
