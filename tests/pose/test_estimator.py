"""PoseEstimator: follows odometry when scans are useless, corrects biased odometry with scans, exposes
the contract used by the glass mapper and the runtime."""

from dataclasses import replace

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid, OccupancyParams
from glassmap.pose import EstimatorConfig, PoseEstimator
from glassmap.pose.motion import compose
from glassmap.types import LaserGeometry, Odometry, PoseEstimate, Scan
from tests.pose.synth import make_scan, room_with_corner

GEOM = LaserGeometry()


def _scan(ranges, stamp):
    return Scan(stamp=stamp, ranges=np.asarray(ranges, dtype=float), intensities=None, geometry=GEOM)


@pytest.mark.parametrize("kind", ["empty", "all_inf", "all_nan", "too_short"])
def test_degenerate_scans_fall_back_to_odometry_with_growing_covariance(kind):
    est = PoseEstimator(EstimatorConfig(keyframe_distance=0.0, keyframe_angle=0.0))  # every scan is a key scan
    n = GEOM.n_beams
    bad = {"empty": np.zeros(0), "all_inf": np.full(n, np.inf), "all_nan": np.full(n, np.nan),
           "too_short": np.full(n, 0.01)}[kind]
    traces = []
    for k in range(11):
        t = 0.1 * k
        est.predict(Odometry(stamp=t, x=0.05 * k, y=0.0, yaw=0.02 * k, v=0.5, omega=0.2))
        e = est.update(_scan(bad, t))
        traces.append(np.trace(e.covariance))
    assert e.x == pytest.approx(0.5, abs=1e-9) and e.yaw == pytest.approx(0.2, abs=1e-9)
    assert np.all(np.diff(traces) > 0)  # never shrinks without a match
    assert est.stats.matched == 0 and est.stats.no_match == 11
    assert np.all(np.isfinite(e.covariance)) and np.all(np.linalg.eigvalsh(e.covariance) > 0)


def test_no_odometry_yet_keeps_the_initial_pose():
    est = PoseEstimator(EstimatorConfig(initial_pose=(1.0, 2.0, 0.5)))
    e = est.update(_scan(np.full(GEOM.n_beams, np.inf), 3.0))
    assert e.pose == pytest.approx([1.0, 2.0, 0.5]) and e.stamp == 3.0


def test_scans_correct_biased_odometry_in_a_room():
    """Odometry over-counts rotation by 5 % and distance by 3 % (8 cm off after 6 s); matching keeps the pose
    within 2 cm."""
    segs = room_with_corner()
    mount = np.array([0.1, 0.0, 0.0])
    est = PoseEstimator(EstimatorConfig(laser_mount=tuple(mount), initial_pose=(-1.5, -1.0, 0.0)))
    rng = np.random.default_rng(3)
    true = np.array([-1.5, -1.0, 0.0])
    odom = np.zeros(3)
    errs, odo_errs = [], []
    dt = 0.025
    for k in range(240):
        v, w = 0.4, (0.6 if 60 <= k < 140 else 0.0)
        step = np.array([v * dt, 0.0, w * dt])
        if k > 0:
            true = compose(true, step)
            odom = compose(odom, np.array([1.03 * step[0], 0.0, 1.05 * step[2]]))
        t = k * dt
        est.predict(Odometry(stamp=t, x=odom[0], y=odom[1], yaw=odom[2], v=v, omega=w))
        e = est.update(make_scan(segs, compose(true, mount), stamp=t, noise=0.01, rng=rng))
        errs.append(np.hypot(e.x - true[0], e.y - true[1]))
        odo_errs.append(np.hypot(*(compose(np.array([-1.5, -1.0, 0.0]), odom)[:2] - true[:2])))
    # 1 cm per scan: the motion filter (5 cm / 2 deg) makes about every 4th-5th scan a key scan; every scan
    # still gets a pose (odometry between key scans)
    assert 40 < est.stats.keyframes < 80 and est.stats.matched > 0.8 * est.stats.keyframes
    assert max(errs) < 0.02 and odo_errs[-1] > 0.07
    assert abs(float(e.yaw - true[2])) < np.radians(0.75)  # odometry: 5 % of 1.2 rad = 3.4 deg off
    assert abs(float(odom[2] - true[2])) > np.radians(3.0)


def test_registration_sigma_formula():
    est = PoseEstimator(EstimatorConfig(laser_mount=(0.0, 0.0, 0.0), range_sigma=0.01, range_sigma_per_m=0.0))
    cov = np.diag([0.03 ** 2, 0.02 ** 2, np.radians(1.0) ** 2])
    e = PoseEstimate(stamp=0.0, x=0.0, y=0.0, yaw=0.0, covariance=cov)
    r = np.array([0.0, 1.0, 10.0, np.inf, np.nan])
    s = est.registration_sigma(e, r)
    expect = np.sqrt(0.03 ** 2 + (r[:3] * np.radians(1.0)) ** 2 + 0.01 ** 2)
    assert s[:3] == pytest.approx(expect)
    assert np.isnan(s[3:]).all()
    assert s[2] == pytest.approx(0.1774, abs=1e-3)  # 10 m at 1 deg: about 17.5 cm


def test_laser_pose_applies_the_mount_offset():
    est = PoseEstimator(EstimatorConfig(laser_mount=(0.1, 0.0, 0.0)))
    e = PoseEstimate(stamp=0.0, x=1.0, y=2.0, yaw=np.pi / 2)
    assert est.laser_pose(e) == pytest.approx([1.0, 2.1, np.pi / 2])
    e.covariance = np.diag([0.0, 0.0, 0.01 ** 2])
    lc = est.laser_covariance(e)
    assert lc[0, 0] == pytest.approx((0.1 * 0.01) ** 2)  # yaw error swings the laser sideways (x here)


def test_scan_is_integrated_into_the_shared_grid_at_the_estimated_pose():
    est = PoseEstimator(EstimatorConfig(initial_pose=(0.0, 0.0, 0.0), laser_mount=(0.0, 0.0, 0.0)))
    segs = room_with_corner()
    est.update(make_scan(segs, np.zeros(3)))
    occ = est.occupancy
    ix, iy = occ.grid.world_to_cell(np.array([3.01, 0.0]))  # the east wall at x = 3
    assert occ.occupied()[iy, ix]
    assert occ.free()[occ.grid.world_to_cell(np.array([1.0, -1.0]))[::-1].tolist()[0],
                      occ.grid.world_to_cell(np.array([1.0, -1.0]))[0]] == False  # one scan: not yet "free"


def test_glass_weights_down_weight_beams_ending_on_glass_cells():
    est = PoseEstimator(EstimatorConfig(glass_min_weight=0.1))
    g = est.occupancy.grid
    g.add_layer("glass", 0.0, np.float32)
    ix, iy = g.world_to_cell(np.array([2.0, 0.0]))
    g["glass"][iy, ix] = np.log(0.99 / 0.01)  # p = 0.99
    jx, jy = g.world_to_cell(np.array([0.0, 2.0]))
    g["glass"][jy, jx] = np.log(0.2 / 0.8)  # p = 0.2: not glass
    w = est.glass_weights(np.zeros(3), np.array([0.0, np.pi / 2, 0.0]), np.array([2.01, 2.01, np.nan]))
    assert w[0] == pytest.approx(1 - 0.9 * 0.98, abs=1e-6)
    assert w[1] == 1.0 and w[2] == 1.0
    mask = est.glass_protect_mask()
    assert mask[iy, ix] and mask.sum() == 1


def _seen_through_glass_sampled(est, laser_pose, angles, reach):
    """The dense numpy form of the behind-glass test (every beam sampled at half-cell steps to the longest reach,
    each sample's p(glass) looked up): the reference for the compiled walk."""
    g = est.occupancy.grid
    u = np.stack([np.cos(laser_pose[2] + angles), np.sin(laser_pose[2] + angles)], axis=1)
    steps = np.arange(0.0, float(reach.max()) + g.resolution, 0.5 * g.resolution)
    inside = steps[None, :] < reach[:, None]
    xy = laser_pose[:2][None, None, :] + steps[None, :, None] * u[:, None, :]
    pg = est.glass_probability_at(xy.reshape(-1, 2)).reshape(inside.shape)
    return np.any(inside & (pg > 0.5), axis=1)


@pytest.mark.parametrize("seed", range(5))
def test_beams_seen_through_glass_are_those_the_sampled_path_finds(seed):
    """The compiled walk along each beam (stopping at its first glass cell) flags the same beams as sampling
    every path densely: random glass log-odds (some panes, some doubtful cells, some at exactly 0), beams of
    random length from a random pose, some leaving the grid."""
    from glassmap.pose.estimator_jit import seen_through_glass

    rng = np.random.default_rng(seed)
    est = PoseEstimator(EstimatorConfig())
    g = est.occupancy.grid
    g.add_layer("glass", 0.0, np.float32)
    lo = g["glass"]
    lo[:] = rng.choice(np.array([0.0, -2.0, 3.0, 1e-30], dtype=np.float32), size=lo.shape, p=[0.6, 0.3, 0.05, 0.05])
    pose = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi)])
    angles = np.linspace(-2.3, 2.3, 200)
    reach = np.maximum(rng.uniform(-0.5, 25.0, angles.size), 0.0)
    u = np.stack([np.cos(pose[2] + angles), np.sin(pose[2] + angles)], axis=1)
    steps = np.arange(0.0, float(reach.max()) + g.resolution, 0.5 * g.resolution)
    got = seen_through_glass(lo, float(g.origin[0]), float(g.origin[1]), float(g.resolution), float(pose[0]),
                             float(pose[1]), np.ascontiguousarray(u[:, 0]), np.ascontiguousarray(u[:, 1]), reach, steps)
    want = _seen_through_glass_sampled(est, pose, angles, reach)
    assert want.any() and not want.all()
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("subcell, limit", [(True, 0.006), (False, None)])
def test_walls_off_cell_centres_do_not_drag_a_standing_robot(subcell, limit):
    """A box whose walls lie 1 cm off cell centres: with sub-cell wall positions a robot standing still
    stays within 6 mm after 15 scans (about 1.5 match sigmas); measuring to cell centres drags it further
    (kept as a reference, with beams clearing up to one cell short of their end points)."""
    segs = np.array([[-3.013, -2.027, 3.011, -2.027], [3.011, -2.027, 3.011, 2.019],
                     [3.011, 2.019, -3.013, 2.019], [-3.013, 2.019, -3.013, -2.027]])
    # (a start known to 1 cm / 10 mrad: with the default 0.1 mm the prior holds the robot and hides the drag)
    est = PoseEstimator(EstimatorConfig(laser_mount=(0, 0, 0), subcell_walls=subcell, field_refresh_scans=1,
                                        keyframe_distance=0.0, keyframe_angle=0.0, initial_sigma=(1e-2,) * 3,
                                        occupancy=OccupancyParams() if subcell else OccupancyParams(hit_margin=0.0, surface_margin=0.0)))
    rng = np.random.default_rng(0)
    for k in range(15):
        e = est.update(make_scan(segs, np.zeros(3), stamp=0.025 * k, noise=0.01, rng=rng))
    err = np.hypot(e.x, e.y)
    if limit is not None:
        assert err < limit
    else:
        assert err > 0.007


def test_nan_stamp_is_refused_with_a_clear_message():
    est = PoseEstimator()
    with pytest.raises(ValueError, match="stamp"):
        est.update(_scan(np.full(GEOM.n_beams, 2.0), float("nan")))


def test_without_integration_the_caller_updates_the_grid_and_matching_still_works():
    """integrate=False (the glass mapper updates the shared grid): the estimator still keeps its per-cell
    bookkeeping and matches against what the caller integrated."""
    segs = room_with_corner()
    est = PoseEstimator(EstimatorConfig(integrate=False, laser_mount=(0.0, 0.0, 0.0), keyframe_distance=0.0,
                                        keyframe_angle=0.0))
    rng = np.random.default_rng(1)
    for k in range(30):
        est.predict(Odometry(stamp=0.025 * k, x=0.0, y=0.0, yaw=0.0))
        scan = make_scan(segs, np.zeros(3), stamp=0.025 * k, noise=0.01, rng=rng)
        e = est.update(scan)
        est.occupancy.integrate(est.laser_pose(e), scan.angles, scan.ranges)  # what the mapper would do
    assert est.occupancy.grid["pose_hit_n"].sum() > 30 * 500
    assert est.stats.matched >= 15 and np.hypot(e.x, e.y) < 0.01  # the field is rebuilt every 10 scans


def _standing_or_moving(cfg, step_m, n=40):
    """n scans in the room, the robot advancing step_m per scan (odometry exact); returns the estimator and the
    key-scan flags."""
    segs = room_with_corner()
    est = PoseEstimator(cfg)
    rng = np.random.default_rng(5)
    keys = []
    for k in range(n):
        x = -1.5 + step_m * k
        est.predict(Odometry(stamp=0.025 * k, x=step_m * k, y=0.0, yaw=0.0))
        est.update(make_scan(segs, np.array([x, -1.0, 0.0]), stamp=0.025 * k, noise=0.01, rng=rng))
        keys.append(est.stats.last_keyframe)
    return est, np.array(keys)


def test_motion_filter_matches_and_integrates_only_key_scans():
    cfg = EstimatorConfig(laser_mount=(0.0, 0.0, 0.0), initial_pose=(-1.5, -1.0, 0.0), keyframe_distance=0.05,
                          keyframe_angle=np.radians(2.0), keyframe_max_scans=15)
    # standing still: the first scan, then one forced key scan every 15 scans
    est, keys = _standing_or_moving(cfg, 0.0)
    assert np.flatnonzero(keys).tolist() == [0, 15, 30]
    assert est.stats.scans == 40 and est.stats.keyframes == 3
    # only key scans reach the grid: 3 scans, every beam of the closed room ends on a wall
    assert est.occupancy.grid["pose_hit_n"].sum() == 3 * GEOM.n_beams
    # 2 cm per scan: a key scan every 3rd scan (6 cm >= 5 cm)
    _, keys = _standing_or_moving(cfg, 0.02)
    assert np.flatnonzero(keys).tolist() == list(range(0, 40, 3))
    # the old behaviour: every scan is a key scan
    est, keys = _standing_or_moving(replace(cfg, keyframe_distance=0.0, keyframe_angle=0.0), 0.0)
    assert keys.all() and est.stats.keyframes == 40


def test_bad_keyframe_settings_are_refused():
    with pytest.raises(ValueError, match="keyframe"):
        EstimatorConfig(keyframe_distance=-0.1)


def test_the_second_key_scan_is_matched_even_when_the_grid_did_not_grow():
    """The first field is built as soon as a scan is in the grid, not after field_refresh_scans key scans
    (those would be placed by odometry alone, and the map would keep their errors)."""
    segs = room_with_corner()
    grid = MapGrid(resolution=0.05, origin=(-10.0, -10.0), shape=(400, 400))  # holds the room already
    est = PoseEstimator(EstimatorConfig(laser_mount=(0.0, 0.0, 0.0), keyframe_distance=0.0, keyframe_angle=0.0),
                        OccupancyGrid(grid))
    rng = np.random.default_rng(2)
    for k in range(3):
        est.predict(Odometry(stamp=0.025 * k, x=0.0, y=0.0, yaw=0.0))
        est.update(make_scan(segs, np.zeros(3), stamp=0.025 * k, noise=0.01, rng=rng))
    assert est.occupancy.grid.generation == 0  # the grid never grew: only the new rule rebuilt the field
    assert est.stats.no_match == 1 and est.stats.matched == 2


def test_scans_after_the_newest_odometry_report_the_extrapolation_error():
    """Odometry at 10 Hz, scans at 40 Hz: a scan 75 ms after the newest message is predicted with that
    message's velocity, whose yaw-rate error (0.1 rad/s by default) turns it by up to 7.5 mrad; the reported
    covariance says so, and drops back when the next message arrives (the filter's own is unchanged)."""
    est = PoseEstimator(EstimatorConfig(laser_mount=(0.0, 0.0, 0.0), map_uncertainty="off"))
    inf = np.full(GEOM.n_beams, np.inf)
    est.predict(Odometry(stamp=0.0, x=0.0, y=0.0, yaw=0.0, v=0.5, omega=0.0))
    e0 = est.update(_scan(inf, 0.0))
    e1 = est.update(_scan(inf, 0.075))
    ekf_yaw = est.ekf.cov[2, 2]
    assert e1.covariance[2, 2] - ekf_yaw == pytest.approx((0.1 * 0.075) ** 2, rel=1e-6)
    assert e1.covariance[1, 1] > e0.covariance[1, 1] + (0.5 * 0.5 * 0.075 * 0.1 * 0.075) ** 2 * 0.99
    est.predict(Odometry(stamp=0.1, x=0.05, y=0.0, yaw=0.0, v=0.5, omega=0.0))
    e2 = est.update(_scan(inf, 0.1))
    assert e2.covariance[2, 2] == pytest.approx(est.ekf.cov[2, 2])


def test_scan_relative_covariance_follows_the_filter_and_hands_out_copies():
    est = PoseEstimator(EstimatorConfig())
    first = est.scan_relative_covariance()
    first[:] = 99.0  # a caller writing into its copy changes nothing
    again = est.scan_relative_covariance()
    assert np.array_equal(again, est.ekf.actual_cov)
    est.ekf.actual_cov = est.ekf.actual_cov + np.eye(3) * 1e-2  # a new state is seen
    assert np.array_equal(est.scan_relative_covariance(), again + np.eye(3) * 1e-2)


@pytest.mark.parametrize("no_return_range", [0.0, 4.0])
def test_grid_holds_scan_only_when_ensure_scan_extent_would_not_grow(no_return_range):
    # the estimator skips OccupancyGrid.ensure_scan_extent when its own end points say the grid holds the
    # scan: that must never skip a growth, and should skip where the scan is well inside
    rng = np.random.default_rng(8)
    skipped = 0
    for _ in range(300):
        occ = OccupancyGrid(MapGrid(0.1, (-3.0, -3.0), (60, 60), grow_step_m=1.0),
                            replace(EstimatorConfig().occupancy, no_return_range=no_return_range))
        est = PoseEstimator(EstimatorConfig(integrate=False), occupancy=occ)
        est.ekf.pose = np.array([*rng.uniform(-2.5, 2.5, 2), rng.uniform(-np.pi, np.pi)])
        angles = np.sort(rng.uniform(-2.4, 2.4, 40))
        ranges = rng.uniform(-0.2, rng.choice([0.5, 2.5]), 40)
        ranges[rng.random(40) < 0.05] = np.inf
        ranges[rng.random(40) < 0.05] = np.nan
        holds = est._grid_holds_scan(est._end_points(angles, ranges, 2.2), ranges)
        grew = occ.ensure_scan_extent(est.laser_pose_of(est.scan_pose()), angles, ranges, 2.2)
        assert not (holds and grew)
        skipped += holds
    assert skipped > 5  # (with no_return_range > 0, only scans without an inf range can skip)


def _laps(config: EstimatorConfig, laps: int) -> tuple[PoseEstimator, list[np.ndarray]]:
    """Circles of 1 m radius in the room (6.3 m a lap, at 0.5 m/s), odometry 3 % long: the reported
    covariance at the start of each lap."""
    segs = room_with_corner()
    mount = np.array([0.1, 0.0, 0.0])
    start = np.array([-0.5, -0.5, 0.0])
    est = PoseEstimator(replace(config, laser_mount=tuple(mount), initial_pose=tuple(start)))
    rng = np.random.default_rng(5)
    dt, v, w = 0.025, 0.5, 0.5
    per_lap = int(round(2 * np.pi / w / dt))
    true, odom, at_start = start.copy(), np.zeros(3), []
    for k in range(laps * per_lap + 1):
        if k > 0:
            true = compose(true, np.array([v * dt, 0.0, w * dt]))
            odom = compose(odom, np.array([1.03 * v * dt, 0.0, w * dt]))
        est.predict(Odometry(stamp=k * dt, x=odom[0], y=odom[1], yaw=odom[2], v=v, omega=w))
        e = est.update(make_scan(segs, compose(true, mount), stamp=k * dt, noise=0.01, rng=rng))
        if k % per_lap == 0:
            at_start.append(e.covariance)
    return est, at_start


def test_coming_back_onto_its_own_map_the_reported_covariance_stops_growing():
    """Lap after lap the key scans match the cells the first laps placed: with revisits (ChainConfig.revisit_gap,
    here 3 m) the reported covariance at the start of a lap stops growing; compounding the steps alone it grows
    with every lap."""
    cfg = EstimatorConfig()
    est, revisit = _laps(replace(cfg, chain=replace(cfg.chain, revisit_gap=3.0, scale_sigma=0.0)), 4)
    _, plain = _laps(replace(cfg, chain=replace(cfg.chain, revisit_gap=0.0, scale_sigma=0.0)), 4)
    assert est.chain.revisits > 0.5 * est.stats.keyframes
    assert est.last_key_scan.anchors is not None and est.last_key_scan.anchors.size > 50
    trace = [np.trace(c[:2, :2]) for c in revisit]
    grown = [np.trace(c[:2, :2]) for c in plain]
    assert grown[-1] > 1.5 * grown[2] and np.all(np.diff(grown) > 0)
    assert trace[-1] < 1.2 * trace[2] and trace[-1] < 0.5 * grown[-1]
