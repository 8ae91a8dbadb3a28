"""Odometry interpolation, SE(2) algebra, the motion-noise model and the EKF."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from glassmap.pose.filter import PoseEKF
from glassmap.pose.motion import MotionNoise, OdometryBuffer, compose, compose_jacobians, deskew, relative
from glassmap.types import Odometry

poses = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-np.pi, np.pi)).map(np.array)


@settings(max_examples=200, deadline=None)
@given(poses, poses)
def test_relative_inverts_compose(a, b):
    back = compose(a, relative(a, b))
    assert back[:2] == pytest.approx(b[:2], abs=1e-9)
    assert np.cos(back[2] - b[2]) == pytest.approx(1.0)


@settings(max_examples=50, deadline=None)
@given(poses, poses)
def test_compose_jacobians_match_finite_differences(a, b):
    ja, jb = compose_jacobians(a, b)
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        num_a = (compose(a + d, b) - compose(a - d, b)) / (2 * eps)
        num_b = (compose(a, b + d) - compose(a, b - d)) / (2 * eps)
        num_a[2] = np.angle(np.exp(1j * num_a[2] * 2 * eps)) / (2 * eps)
        num_b[2] = np.angle(np.exp(1j * num_b[2] * 2 * eps)) / (2 * eps)
        assert ja[:, i] == pytest.approx(num_a, abs=1e-5)
        assert jb[:, i] == pytest.approx(num_b, abs=1e-5)


def test_buffer_interpolates_extrapolates_and_holds():
    buf = OdometryBuffer(max_extrapolation=0.2)
    buf.add(Odometry(stamp=1.0, x=0.0, y=0.0, yaw=3.0))
    buf.add(Odometry(stamp=2.0, x=1.0, y=2.0, yaw=-3.0, v=1.0, omega=0.0))
    p = buf.pose_at(1.5)
    assert p[:2] == pytest.approx([0.5, 1.0])
    assert abs(abs(p[2]) - np.pi) < 1e-9  # shortest arc through +-pi, not through 0
    assert buf.pose_at(0.0) == pytest.approx([0.0, 0.0, 3.0])  # before the first: held
    ahead = buf.pose_at(2.1)  # constant velocity along the heading (-3 rad)
    assert ahead[:2] == pytest.approx([1.0 + 0.1 * np.cos(-3.0), 2.0 + 0.1 * np.sin(-3.0)])
    assert buf.pose_at(5.0) == pytest.approx(buf.pose_at(2.2))  # extrapolation capped
    buf.add(Odometry(stamp=1.5, x=9.0, y=9.0, yaw=0.0))  # out of order: inserted in place
    assert buf.pose_at(1.5)[:2] == pytest.approx([9.0, 9.0])
    with pytest.raises(LookupError):
        OdometryBuffer().pose_at(0.0)
    with pytest.raises(ValueError, match="non-finite"):
        buf.add(Odometry(stamp=3.0, x=np.nan, y=0.0, yaw=0.0))


def test_motion_noise_is_aligned_with_travel_and_grows():
    mn = MotionNoise()
    c = mn.covariance(np.array([0.0, 1.0, 0.0]), 0.0)  # 1 m along +y
    assert c[1, 1] > c[0, 0] > 0  # along-track (scale) error dominates
    assert c[1, 1] == pytest.approx(0.02 ** 2 + 1.5e-5, rel=1e-6)
    assert mn.covariance(np.zeros(3), 1.0)[0, 0] == pytest.approx(0.002 ** 2)  # standing still: time term
    assert mn.covariance(np.array([0, 0, np.pi / 2]), 0.0)[2, 2] > mn.covariance(np.array([0, 0, 0.1]), 0.0)[2, 2]


def test_ekf_fuses_equal_uncertainties_to_the_midpoint_and_halves_the_covariance():
    ekf = PoseEKF(np.array([0.0, 0.0, 0.0]), np.eye(3) * 0.04)
    d2 = ekf.correct(np.array([0.2, -0.2, 0.1]), np.eye(3) * 0.04)
    assert ekf.pose == pytest.approx([0.1, -0.1, 0.05])
    assert ekf.cov == pytest.approx(np.eye(3) * 0.02)
    assert d2 == pytest.approx((0.04 + 0.04 + 0.01) / 0.08)
    # yaw innovation wraps: 179 deg and -179 deg are 2 deg apart
    ekf = PoseEKF(np.array([0.0, 0.0, np.radians(179)]), np.eye(3) * 0.01)
    ekf.correct(np.array([0.0, 0.0, np.radians(-179)]), np.eye(3) * 0.01)
    assert abs(ekf.pose[2]) == pytest.approx(np.pi, abs=1e-9)


def test_ekf_prediction_rotates_the_motion_and_grows_the_covariance():
    ekf = PoseEKF(np.array([1.0, 1.0, np.pi / 2]), np.diag([0.0, 0.0, 0.01]))
    ekf.predict(np.array([1.0, 0.0, 0.0]), np.zeros((3, 3)))
    assert ekf.pose == pytest.approx([1.0, 2.0, np.pi / 2])
    # a yaw uncertainty of 0.1 rad turns into 0.1 m sideways (x) after 1 m
    assert ekf.cov[0, 0] == pytest.approx(0.01)


def _skewed_scan(v: float, w: float, mount: np.ndarray, r: float = 3.0):
    """A scan of world points taken while the base moves with constant (v, w) from the origin: beam k from
    the base pose at t_k = k * time_increment. Returns (angles, ranges, the same points seen from the laser
    at t_0 as (angles, ranges), the base motion over the sweep, fraction of the sweep per beam)."""
    from glassmap.types import LaserGeometry

    g = LaserGeometry()
    n = g.n_beams
    t = np.arange(n) * g.time_increment
    angles = g.angles
    ranges = r + 0.5 * np.sin(3 * angles)

    def base_at(tk):
        if abs(w) < 1e-12:
            return np.array([v * tk, 0.0, 0.0])
        return np.array([v / w * np.sin(w * tk), v / w * (1 - np.cos(w * tk)), w * tk])

    laser0 = compose(base_at(0.0), mount)
    exp_a, exp_r = np.zeros(n), np.zeros(n)
    for k in range(n):  # test only: the reference, beam by beam
        lk = compose(base_at(t[k]), mount)
        world = compose(lk, np.array([ranges[k] * np.cos(angles[k]), ranges[k] * np.sin(angles[k]), 0.0]))
        seen = relative(laser0, world)
        exp_a[k], exp_r[k] = np.arctan2(seen[1], seen[0]), np.hypot(seen[0], seen[1])
    delta = base_at(t[-1])
    return angles, ranges, exp_a, exp_r, delta, t / t[-1]


@pytest.mark.parametrize("v, w, tol", [(0.0, 1.0, 1e-9), (0.5, 0.0, 1e-9), (0.5, 1.0, 5e-4)])
def test_deskew_with_a_known_motion_gives_the_points_seen_from_the_first_beam(v, w, tol):
    """Turning in place at 1 rad/s (57 deg/s) bends a UTM-30LX scan by about 1 deg end to end, driving at
    0.5 m/s shifts its last beams by 9 mm; de-skewing with the known motion gives back the points as seen
    from the laser at the first beam (exactly for a pure turn or a straight line, to a fraction of a mm on
    an arc)."""
    mount = np.array([0.1, 0.0, 0.0])
    angles, ranges, exp_a, exp_r, delta, frac = _skewed_scan(v, w, mount)
    raw = np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], axis=1)
    exp = np.stack([exp_r * np.cos(exp_a), exp_r * np.sin(exp_a)], axis=1)
    assert np.abs(raw - exp).max() > 0.008  # the skew is real
    a, r = deskew(angles, ranges, mount, delta, frac)
    got = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    assert np.abs(got - exp).max() < tol


def test_deskew_leaves_invalid_beams_alone():
    angles = np.array([-0.5, 0.0, 0.5])
    ranges = np.array([np.nan, np.inf, 2.0])
    a, r = deskew(angles, ranges, np.zeros(3), np.array([0.01, 0.0, 0.02]), np.array([0.0, 0.5, 1.0]))
    assert np.isnan(r[0]) and np.isposinf(r[1]) and np.isfinite(r[2])
    assert a[0] == -0.5 and a[1] == 0.0


def test_estimator_deskews_key_scans_with_its_odometry():
    """With ``deskew`` the estimator takes the motion over the sweep from the buffered odometry: turning at
    1 rad/s, the last beam is rotated by about 1 deg and the first one not at all."""
    from glassmap.pose import EstimatorConfig, PoseEstimator
    from glassmap.types import LaserGeometry, Odometry, Scan

    est = PoseEstimator(EstimatorConfig(laser_mount=(0.0, 0.0, 0.0), deskew=True))
    for k in range(3):
        est.predict(Odometry(stamp=0.1 * k, x=0.0, y=0.0, yaw=0.1 * k, v=0.0, omega=1.0))
    g = LaserGeometry()
    scan = Scan(stamp=0.2, ranges=np.full(g.n_beams, 2.0), intensities=None, geometry=g)
    a, r = est.deskewed(scan)
    sweep = g.time_increment * (g.n_beams - 1)
    assert a[0] == pytest.approx(g.angles[0], abs=1e-12)
    assert a[-1] - g.angles[-1] == pytest.approx(sweep * 1.0, rel=1e-6)  # extrapolated with omega
    assert np.allclose(r, 2.0)


def test_compose_covariance_is_the_first_order_spread_of_compose():
    """A pose 1 m along x turned by 90 deg: a yaw error of the first pose moves the composed one sideways by the
    lever arm, the second pose's x error appears along the first pose's y."""
    from glassmap.pose.motion import compose_covariance

    a, b = np.array([0.0, 0.0, np.pi / 2]), np.array([1.0, 0.0, 0.0])
    cov = compose_covariance(a, b, np.diag([0.0, 0.0, 1e-4]), np.diag([4e-4, 0.0, 0.0]))
    np.testing.assert_allclose(cov, np.array([[1e-4, 0.0, -1e-4], [0.0, 4e-4, 0.0], [-1e-4, 0.0, 1e-4]]), atol=1e-15)
