"""Extended Kalman filter over the base pose (x, y, yaw) in the map frame.

Prediction composes the odometry increment (base frame) onto the state and propagates the covariance with
the SE(2) Jacobians; correction fuses a full-pose measurement (the scan match) with its covariance, using
the Joseph form so the covariance stays symmetric positive definite.

Correlated measurements. The filter's gain treats every match as independent, but consecutive scans
matched against the same map cells share part of their error, and averaging them does not remove it. So
the filter also carries ``actual_cov``, the covariance of its error when a match's error has correlation
``rho`` with the previous match's (a "consider" covariance, as in the Schmidt-Kalman filter: the estimate
and the gain are unchanged, only the covariance is honest about them). With ``cross`` = Cov(state error,
previous match error), a correction with gain K gives
``actual_cov = (I-K) P (I-K)^T + K R K^T + (I-K) rho cross K^T + K rho cross^T (I-K)^T`` and
``cross = (I-K) rho cross + K R``; rho = 0 gives the ordinary Joseph form.
"""

from __future__ import annotations

import numpy as np

from glassmap.pose.filter_jit import predict as predict_step
from glassmap.types import wrap_angle


class PoseEKF:
    """State ``pose`` (3,) (m, m, rad) and ``cov`` (3, 3) (m^2, rad^2), map frame; ``actual_cov`` (3, 3):
    the covariance of the state's error allowing for correlated matches (see the module docstring)."""

    def __init__(self, pose: np.ndarray, cov: np.ndarray) -> None:
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.cov = np.asarray(cov, dtype=np.float64).copy()
        if self.pose.shape != (3,) or self.cov.shape != (3, 3):
            raise ValueError("PoseEKF needs a (3,) pose and a (3, 3) covariance")
        self.actual_cov = self.cov.copy()
        self.cross = np.zeros((3, 3))  # Cov(state error, error of the last fused measurement)

    def predict(self, delta: np.ndarray, q: np.ndarray) -> None:
        """Apply the relative motion ``delta`` (base frame at the previous pose) with covariance ``q``:
        pose (+) delta, P <- Ja P Ja^T + Jb q Jb^T (symmetrized; the same for ``actual_cov``), cross <- Ja
        cross, with the Jacobians of :func:`~glassmap.pose.motion.compose_jacobians` (one compiled step,
        :func:`glassmap.pose.filter_jit.predict`)."""
        self.pose, self.cov, self.actual_cov, self.cross = predict_step(
            self.pose, np.asarray(delta, dtype=np.float64), np.asarray(q, dtype=np.float64), self.cov,
            self.actual_cov, self.cross)

    def innovation(self, z: np.ndarray, r: np.ndarray, h: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, float]:
        """(innovation y, innovation covariance S, squared Mahalanobis distance y^T S^-1 y) of a pose
        measurement ``z`` (3,) with covariance ``r``; with ``h`` (k, 3) (orthonormal rows) only the k
        directions ``h @ pose`` are measured: y = h (z - pose), S = h (P + r) h^T."""
        y = np.asarray(z, dtype=np.float64) - self.pose
        y[2] = float(wrap_angle(y[2]))
        s = self.cov + r
        if h is not None:
            y, s = h @ y, h @ s @ h.T
        return y, s, float(y @ np.linalg.solve(s, y))

    def correct(self, z: np.ndarray, r: np.ndarray, rho: float = 0.0, h: np.ndarray | None = None) -> float:
        """Fuse a direct pose measurement ``z`` (3,) with covariance ``r`` whose error has correlation ``rho``
        (0..1) with that of the previous measurement; returns the squared Mahalanobis distance of the
        innovation. ``h`` (k, 3), orthonormal rows: fuse only the directions ``h @ pose`` (the others are not
        measured: their covariance keeps growing with the prediction), e.g. across a corridor but not
        along it."""
        hm = np.eye(3) if h is None else np.asarray(h, dtype=np.float64)
        y, s, d2 = self.innovation(z, r, None if h is None else hm)
        k = np.linalg.solve(s.T, (self.cov @ hm.T).T).T  # P H^T S^-1 (S symmetric)
        self.pose = self.pose + k @ y
        self.pose[2] = float(wrap_angle(self.pose[2]))
        kh = k @ hm
        ikh = np.eye(3) - kh
        khr = kh @ r @ kh.T
        self.cov = ikh @ self.cov @ ikh.T + khr
        self.cov = 0.5 * (self.cov + self.cov.T)
        c = rho * self.cross
        a = ikh @ self.actual_cov @ ikh.T + khr + ikh @ c @ kh.T + kh @ c.T @ ikh.T
        self.actual_cov = 0.5 * (a + a.T)
        self.cross = ikh @ c + kh @ r
        return d2


def offset_consensus(offsets: list[np.ndarray], covs: list[np.ndarray], dirs: list[np.ndarray]
                     ) -> tuple[np.ndarray, float, int]:
    """Do several pose offsets measure one and the same offset?

    ``offsets[k]`` (3,) (m, m, rad; yaw wrapped) is match k minus the prediction at its time, ``covs[k]``
    (3, 3) its covariance, ``dirs[k]`` (d_k, 3) the directions it measures (rows, as for
    :meth:`PoseEKF.correct`). Returns (the weighted least-squares common offset (3,), zero where no
    match measures it; the chi-square of the offsets about it; its degrees of freedom, the measured
    directions minus the rank of their information). A chi-square far above its degrees of freedom means
    the matches disagree with each other, e.g. several aliases of a repetitive corridor."""
    info, b = np.zeros((3, 3)), np.zeros(3)
    parts = []
    for y, c, h in zip(offsets, covs, dirs):
        u, s_inv = h @ y, np.linalg.inv(h @ c @ h.T)
        info += h.T @ s_inv @ h
        b += h.T @ s_inv @ u
        parts.append((u, s_inv, h))
    mean = np.linalg.pinv(info, hermitian=True) @ b
    chi2 = sum(float((u - h @ mean) @ s_inv @ (u - h @ mean)) for u, s_inv, h in parts)
    dof = sum(h.shape[0] for h in dirs) - int(np.linalg.matrix_rank(info, hermitian=True))
    return mean, chi2, dof
