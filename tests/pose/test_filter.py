"""The pose EKF: Joseph-form correction, and the covariance it reports when matches share their error."""

import numpy as np
import pytest

from glassmap.pose.filter import PoseEKF


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
