"""The pose EKF: Joseph-form correction, the covariance it reports when matches share their error, and the
test of whether rejected matches share one offset from the prediction."""

import numpy as np
import pytest

from glassmap.pose.filter import PoseEKF, offset_consensus


def _fuse_repeatedly(rho: float, n: int = 50) -> PoseEKF:
    ekf = PoseEKF(np.zeros(3), np.diag([1e-4, 1e-4, 1e-4]))
    r = np.diag([9e-6, 9e-6, 1e-6])  # (3 mm)^2, (1 mrad)^2
    for _ in range(n):
        ekf.predict(np.zeros(3), np.zeros((3, 3)))  # standing still: nothing new between the matches
        ekf.correct(np.zeros(3), r, rho)
    return ekf


def test_independent_matches_average_down():
    """n independent matches of variance R: the filter's covariance is R / n, and the actual one the same."""
    ekf = _fuse_repeatedly(0.0)
    assert ekf.cov[0, 0] == pytest.approx(9e-6 / 50, rel=0.02)
    assert np.allclose(ekf.actual_cov, ekf.cov)


def test_matches_sharing_their_error_do_not_average_down():
    """The same map error in every match (rho = 1): averaging 50 of them leaves the error of one, R, while
    the filter's own covariance (its gain assumes independence) still shrinks to R / 50."""
    ekf = _fuse_repeatedly(1.0)
    assert ekf.cov[0, 0] == pytest.approx(9e-6 / 50, rel=0.02)
    assert ekf.actual_cov[0, 0] == pytest.approx(9e-6, rel=0.05)
    assert ekf.actual_cov[2, 2] == pytest.approx(1e-6, rel=0.05)
    half = _fuse_repeatedly(0.5)
    assert ekf.cov[0, 0] < half.actual_cov[0, 0] < ekf.actual_cov[0, 0]


def test_offsets_that_agree_have_one_common_offset_and_no_chi_square():
    cov = np.diag([0.01 ** 2, 0.01 ** 2, 1e-6])
    mean, chi2, dof = offset_consensus([np.array([0.5, -0.2, 0.01])] * 5, [cov] * 5, [np.eye(3)] * 5)
    np.testing.assert_allclose(mean, [0.5, -0.2, 0.01], atol=1e-12)
    assert chi2 == pytest.approx(0.0, abs=1e-12) and dof == 12


def test_alternating_offsets_are_a_large_chi_square():
    """Two aliases 0.3 m apart along x, 1 cm matches: mean (3 * 0.5 + 2 * 0.8) / 5 = 0.62 m and chi-square
    3 * (0.12 / 0.01)^2 + 2 * (0.18 / 0.01)^2 = 1080 on 5 * 3 - 3 = 12 degrees of freedom."""
    cov = np.diag([0.01 ** 2, 0.01 ** 2, 1e-6])
    offsets = [np.array([0.5 + 0.3 * (k % 2), 0.0, 0.0]) for k in range(5)]
    mean, chi2, dof = offset_consensus(offsets, [cov] * 5, [np.eye(3)] * 5)
    np.testing.assert_allclose(mean, [0.62, 0.0, 0.0], atol=1e-12)
    assert chi2 == pytest.approx(1080.0) and dof == 12


def test_partial_offsets_combine_and_unmeasured_directions_stay_zero():
    """One match measures only x, one only y: together they give (x, y), yaw unmeasured (0), and nothing
    is left to test them against each other."""
    cov = np.diag([0.01 ** 2, 0.04 ** 2, 1e-6])
    mean, chi2, dof = offset_consensus([np.array([0.3, 9.0, 1.0]), np.array([9.0, -0.1, 1.0])], [cov, cov],
                                       [np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])])
    np.testing.assert_allclose(mean, [0.3, -0.1, 0.0], atol=1e-12)
    assert chi2 == pytest.approx(0.0, abs=1e-12) and dof == 0
