"""Robot kinematics, acceleration limits, laser mount, odometry error statistics, route following."""

import math

import numpy as np
import pytest

from glassmap.sim.robot import DiffDriveRobot, OdometryNoise, RobotParams, RouteFollower, compose
from glassmap.sim.world import load_world, polyline_clearance


def drive(robot: DiffDriveRobot, v: float, omega: float, seconds: float, dt: float = 0.1) -> None:
    robot.set_velocity(v, omega)
    for _ in range(int(round(seconds / dt))):
        robot.step(dt)


def test_perfect_odometry_matches_truth_and_acceleration_is_limited():
    r = DiffDriveRobot(noise=OdometryNoise.none(), pose0=(1.0, 2.0, math.pi / 2))
    r.set_velocity(0.5, 0.0)
    r.step(0.5)
    assert r.velocity[0] == pytest.approx(0.15)  # 0.3 m/s^2 for 0.5 s
    drive(r, 0.5, 0.0, 10.0)
    assert r.velocity[0] == pytest.approx(0.5)
    # ramp 0 -> 0.5 m/s takes 1.667 s (0.4167 m); 10.5 s in total
    expect = 0.5 * 10.5 - 0.5 * 0.5 / 0.3 / 2
    np.testing.assert_allclose(r.true_pose, [1.0, 2.0 + expect, math.pi / 2], atol=1e-4)  # 20 ms sub-steps
    np.testing.assert_allclose(r.odom_pose, [expect, 0.0, 0.0], atol=1e-4)  # odom frame starts at zero
    assert r.wheel_speeds == pytest.approx((0.5, 0.5))


def test_turn_rate_clamped_and_wheel_speeds():
    p = RobotParams()
    r = DiffDriveRobot(noise=OdometryNoise.none())
    r.set_velocity(5.0, 10.0)
    assert r.command == (p.max_velocity, p.max_rot_velocity)
    r.set_velocity(0.0, math.radians(60))
    for _ in range(40):
        r.step(0.05)
    v, w = r.velocity
    assert w == pytest.approx(math.radians(60))
    left, right = r.wheel_speeds
    assert right - left == pytest.approx(w * p.track)
    with pytest.raises(ValueError):
        r.set_velocity(float("nan"), 0.0)


def test_laser_pose_uses_mount_offset():
    r = DiffDriveRobot(RobotParams(laser_offset=(0.1, 0.05, 0.0)), pose0=(2.0, 3.0, math.pi / 2))
    np.testing.assert_allclose(r.laser_pose(), [2.0 - 0.05, 3.1, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(compose([0, 0, math.pi], [1, 0, math.pi]), [-1, 0, 0], atol=1e-12)


def test_odometry_error_statistics_match_the_model():
    """Straight 4 m drives: heading error mean (eR - eL) * L / track' and std slip * sqrt(2 L) / track'."""
    noise = OdometryNoise(left_scale_error=0.01, right_scale_error=-0.01, track_error=0.05, slip_std=0.01)
    params = RobotParams(max_substep=0.1)
    rng = np.random.default_rng(42)
    n = 400
    head, dist, travelled = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        r = DiffDriveRobot(params, noise, rng=rng)
        r.set_velocity(0.5, 0.0)
        for _ in range(80):
            r.step(0.1)
        travelled[i] = r.distance
        head[i] = r.odom_pose[2]
        dist[i] = np.hypot(*r.odom_pose[:2])
    L = travelled.mean()
    assert np.ptp(travelled) < 1e-9  # the true motion is not affected by odometry errors
    track_odom = params.track * (1 + noise.track_error)
    mean_expect = (noise.right_scale_error - noise.left_scale_error) * L / track_odom
    std_expect = noise.slip_std * math.sqrt(2 * L) / track_odom
    assert head.mean() == pytest.approx(mean_expect, abs=4 * std_expect / math.sqrt(n))
    assert head.std() == pytest.approx(std_expect, rel=0.12)
    scale = 1 + (noise.left_scale_error + noise.right_scale_error) / 2
    assert dist.mean() == pytest.approx(L * scale, abs=0.01)


def test_track_error_scales_turns():
    noise = OdometryNoise(0.0, 0.0, track_error=0.05, slip_std=0.0)
    r = DiffDriveRobot(noise=noise)
    drive(r, 0.0, math.radians(45), 2.0, dt=0.05)
    r.set_velocity(0.0, 0.0)
    for _ in range(40):
        r.step(0.05)
    true_turn = r.true_pose[2]
    assert r.odom_pose[2] == pytest.approx(true_turn / 1.05, rel=1e-6)


def test_same_seed_same_odometry():
    def run(seed):
        r = DiffDriveRobot(rng=np.random.default_rng(seed))
        drive(r, 0.4, 0.2, 5.0)
        return r.odom_pose

    np.testing.assert_array_equal(run(1), run(1))
    assert not np.array_equal(run(1), run(2))


def test_route_follower_drives_the_office_route_within_limits():
    w = load_world("office")
    wp = w.route("short")
    d0 = wp[1] - wp[0]
    r = DiffDriveRobot(pose0=(wp[0][0], wp[0][1], math.atan2(d0[1], d0[0])), rng=np.random.default_rng(0))
    f = RouteFollower(wp)
    path, vmax, wmax = [], 0.0, 0.0
    for _ in range(int(120 / 0.05)):
        if f.done:
            break
        r.set_velocity(*f.command(r.true_pose))
        r.step(0.05)
        path.append(r.true_pose[:2])
        vmax, wmax = max(vmax, abs(r.velocity[0])), max(wmax, abs(r.velocity[1]))
    assert f.done
    assert np.hypot(*(r.true_pose[:2] - wp[-1])) < 0.1
    assert vmax <= 0.5 + 1e-9 and wmax <= math.radians(60) + 1e-9
    assert polyline_clearance(np.array(path), w.segments) >= 0.4


def test_route_follower_turns_in_place_at_corners():
    wp = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    r = DiffDriveRobot(noise=OdometryNoise.none())
    f = RouteFollower(wp)
    path = []
    for _ in range(int(60 / 0.05)):
        if f.done:
            break
        r.set_velocity(*f.command(r.true_pose))
        r.step(0.05)
        path.append(r.true_pose[:2])
    assert f.done
    path = np.array(path)
    # never cuts the corner by more than a few centimetres
    dist = np.minimum(np.abs(path[:, 1]), np.abs(path[:, 0] - 2.0))
    assert dist.max() < 0.12
    with pytest.raises(ValueError):
        RouteFollower([[0.0, 0.0]])
