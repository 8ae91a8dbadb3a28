"""Simulated runs: rates, labels, save/load round trip, seeds make runs repeatable."""

import math

import numpy as np
import pytest

from glassmap.sim.dataset import DatasetError, SimRun, simulate_run
from glassmap.sim.world import load_world
from glassmap.types import Odometry, Scan

ROUTE = np.array([[10.0, 1.2], [13.0, 1.2]])  # 3 m along the office's glass facade


@pytest.fixture(scope="module")
def run() -> SimRun:
    return simulate_run(load_world("office"), ROUTE, seed=7)


def test_rates_shapes_and_labels(run: SimRun):
    n = run.geometry.n_beams
    assert run.route_name == "custom" and run.world_name == "office"
    assert run.ranges.shape == (run.n_scans, n) == run.true_range.shape == run.material.shape
    np.testing.assert_allclose(np.diff(run.scan_stamps), 1 / 40)
    np.testing.assert_allclose(np.diff(run.odom_stamps), 1 / 10)
    assert len(run.odom_stamps) == math.ceil(run.n_scans / 4)
    assert 6.0 < run.duration < 12.0  # 3 m at up to 0.5 m/s with acceleration and stopping
    np.testing.assert_allclose(run.scan_true_poses[-1, :2], ROUTE[-1], atol=0.1)
    # laser mounted 0.1 m ahead of the base
    np.testing.assert_allclose(run.laser_poses[:, 0] - run.scan_true_poses[:, 0], 0.1, atol=1e-3)
    ok = np.isfinite(run.ranges)
    assert run.is_glass[ok].any() and run.crossed_glass.any()
    assert np.all(run.material[run.is_glass] == 1)
    err = run.ranges[ok] - run.true_range[ok]
    assert np.abs(err).max() < 0.2


def test_scans_and_odometry_as_types(run: SimRun):
    s = run.scan(3)
    assert isinstance(s, Scan) and s.stamp == pytest.approx(3 / 40) and s.echoes.shape == (1081, 2)
    odo = run.odometry()
    assert isinstance(odo[0], Odometry) and len(odo) == len(run.odom_stamps)
    assert odo[-1].x == pytest.approx(run.odom_poses[-1, 0])


def test_save_load_round_trip(run: SimRun, tmp_path):
    path = run.save(tmp_path / "r")
    assert path.suffix == ".npz"
    back = SimRun.load(path)
    assert (back.world_name, back.route_name, back.seed, back.geometry) == (
        run.world_name, run.route_name, run.seed, run.geometry)
    assert back.params == run.params
    for name in ("ranges", "intensities", "true_range", "material", "incidence", "is_glass", "crossed_glass",
                 "segment", "odom_poses", "odom_true_poses", "laser_poses", "last_echo_range", "route", "is_ghost"):
        np.testing.assert_array_equal(getattr(back, name), getattr(run, name), err_msg=name)


def test_load_rejects_other_files(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, a=np.zeros(3))
    with pytest.raises(DatasetError, match="not a glassmap simulator dataset"):
        SimRun.load(p)
    with pytest.raises(DatasetError, match="cannot read"):
        SimRun.load(tmp_path / "missing.npz")


def test_seeds_make_runs_repeatable(run: SimRun):
    again = simulate_run(load_world("office"), ROUTE, seed=7)
    np.testing.assert_array_equal(again.ranges, run.ranges)
    np.testing.assert_array_equal(again.odom_poses, run.odom_poses)
    other = simulate_run(load_world("office"), ROUTE, seed=8)
    assert not np.array_equal(other.odom_poses, run.odom_poses)


def test_bad_rates_and_unknown_route():
    with pytest.raises(ValueError, match="multiple"):
        simulate_run("room", seed=0, scan_rate=40, odom_rate=15)
    with pytest.raises(ValueError, match="no route 'x'"):
        simulate_run("room", "x")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["office", "glass-corridor", "room", "lobby"])
def test_default_routes_are_driven_without_collision(name):
    from glassmap.sim.world import polyline_clearance

    w = load_world(name)
    run = simulate_run(w, seed=0)
    assert polyline_clearance(run.scan_true_poses[:, :2], w.segments) >= 0.4
    np.testing.assert_allclose(run.scan_true_poses[-1, :2], w.route()[-1], atol=0.1)
    if name == "office":
        assert 60.0 <= run.duration <= 120.0


def test_sweep_motion_moves_the_late_beams_only(run: SimRun):
    """With sweep motion the robot drives on during each sweep: while it moves along the facade, the
    last beams (taken ~19 ms after the first) see the world from a point up to v * 19 ms further on; the
    first beam of each scan is taken at the recorded laser pose, as without it."""
    swept = simulate_run(load_world("office"), ROUTE, seed=7, sweep_motion=True)
    assert swept.params["sweep_motion"] is True and run.params["sweep_motion"] is False
    np.testing.assert_array_equal(swept.laser_poses, run.laser_poses)
    moving = np.flatnonzero(np.hypot(*np.diff(run.laser_poses[:, :2], axis=0).T) > 0.01)
    i = int(moving[len(moving) // 2])
    np.testing.assert_allclose(swept.true_range[i, :30], run.true_range[i, :30], atol=3e-3)
    assert np.nanmax(np.abs(swept.true_range[i, -60:] - run.true_range[i, -60:])) > 3e-3
