"""Odometry interpolation, SE(2) algebra, the motion-noise model and the EKF."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from glassmap.pose.filter import PoseEKF
from glassmap.pose.motion import MotionNoise, OdometryBuffer, compose, compose_jacobians, relative
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
