"""Wheel odometry: a time-ordered buffer interpolated to scan times, SE(2) helpers and the motion-noise model.

Frames: odometry poses are the base in the ``odom`` frame; relative motions are expressed in the base frame
at the start of the motion. Units: metres, radians, seconds.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from glassmap.types import Odometry, wrap_angle


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) composition a (+) b: pose b given in the frame of pose a, expressed in a's parent frame."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], float(wrap_angle(a[2] + b[2]))])


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of b in the frame of a (a^-1 (+) b), so that compose(a, relative(a, b)) == b."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(b[2] - a[2]))])


def compose_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (3x3, 3x3) of compose(a, b) with respect to a and to b."""
    c, s = np.cos(a[2]), np.sin(a[2])
    ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]],
                   [0.0, 1.0, c * b[0] - s * b[1]],
                   [0.0, 0.0, 1.0]])
    jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja, jb


@dataclass(frozen=True)
class MotionNoise:
    """Noise of one relative odometry motion (dx, dy, dyaw) in the base frame, as standard deviations.

    For a motion of translation d (m) and rotation |dyaw| (rad) lasting dt (s), the covariance is diagonal
    in the base frame with

        var_along = (trans_per_m * d)^2 + trans_rw * d + (xy_per_s^2) * dt
        var_lateral = (lateral_per_m * d)^2 + trans_rw * d + (xy_per_s^2) * dt
        var_yaw = (rot_per_rad * |dyaw|)^2 + (rot_per_m * d)^2 + rot_rw_m * d + rot_rw_rad * |dyaw|
                  + (yaw_per_s^2) * dt

    The proportional terms cover systematic wheel errors (scale: ``trans_per_m`` = 2 % of the distance;
    track width: ``rot_per_rad`` = 3 % of the turn; a wheel-radius mismatch curves straight lines:
    ``rot_per_m``), the random-walk terms cover wheel slip (a Pioneer-like base with 5 mm/sqrt(m) slip per
    wheel and a 0.36 m track gives about 1.3e-5 m^2/m along the path and 4e-4 rad^2/m in yaw), and the time
    terms keep the covariance growing while the robot stands still or odometry is stale (wheels slip,
    people push robots).
    """

    trans_per_m: float = 0.02
    lateral_per_m: float = 0.01
    trans_rw: float = 1.5e-5  # m^2 per m travelled
    rot_per_rad: float = 0.03
    rot_per_m: float = 0.01  # rad per m travelled
    rot_rw_m: float = 4e-4  # rad^2 per m travelled
    rot_rw_rad: float = 1e-4  # rad^2 per rad turned
    xy_per_s: float = 0.002  # m / sqrt(s)
    yaw_per_s: float = 0.002  # rad / sqrt(s)

    def covariance(self, delta: np.ndarray, dt: float) -> np.ndarray:
        """3x3 covariance of the relative motion ``delta`` (base frame at the start) over ``dt`` seconds."""
        d = float(np.hypot(delta[0], delta[1]))
        r = abs(float(delta[2]))
        dt = max(float(dt), 0.0)
        var_along = (self.trans_per_m * d) ** 2 + self.trans_rw * d + self.xy_per_s ** 2 * dt
        var_lat = (self.lateral_per_m * d) ** 2 + self.trans_rw * d + self.xy_per_s ** 2 * dt
        var_yaw = ((self.rot_per_rad * r) ** 2 + (self.rot_per_m * d) ** 2 + self.rot_rw_m * d
                   + self.rot_rw_rad * r + self.yaw_per_s ** 2 * dt)
        if d > 1e-9:  # along / lateral axes follow the direction of travel
            c, s = delta[0] / d, delta[1] / d
            rot = np.array([[c, -s], [s, c]])
            xy = rot @ np.diag([var_along, var_lat]) @ rot.T
        else:
            xy = np.diag([var_along, var_lat])
        cov = np.zeros((3, 3))
        cov[:2, :2] = xy
        cov[2, 2] = var_yaw
        return cov


class OdometryBuffer:
    """Time-ordered wheel odometry (odom frame) that answers "where was the base at time t?".

    Inside the buffered span the pose is interpolated linearly in x, y and along the shortest arc in yaw.
    After the newest message it is extrapolated with the newest (v, omega) for at most ``max_extrapolation``
    seconds and then held. Before the oldest message the oldest pose is held. Messages older than
    ``horizon`` seconds behind the newest are dropped. Out-of-order messages are inserted in place.
    """

    def __init__(self, horizon: float = 5.0, max_extrapolation: float = 0.25) -> None:
        if horizon <= 0 or max_extrapolation < 0:
            raise ValueError("horizon must be positive and max_extrapolation non-negative")
        self.horizon = horizon
        self.max_extrapolation = max_extrapolation
        self._t: list[float] = []
        self._pose: list[np.ndarray] = []
        self._vel: list[tuple[float, float]] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def latest_stamp(self) -> float | None:
        return self._t[-1] if self._t else None

    def add(self, odom: Odometry) -> None:
        pose = np.array([odom.x, odom.y, odom.yaw], dtype=np.float64)
        if not (np.all(np.isfinite(pose)) and np.isfinite(odom.stamp)):
            raise ValueError(f"odometry at stamp {odom.stamp} has a non-finite pose {pose}")
        i = bisect.bisect_right(self._t, odom.stamp)
        if i > 0 and self._t[i - 1] == odom.stamp:  # duplicate stamp: keep the newer message
            self._pose[i - 1] = pose
            self._vel[i - 1] = (float(odom.v), float(odom.omega))
        else:
            self._t.insert(i, float(odom.stamp))
            self._pose.insert(i, pose)
            self._vel.insert(i, (float(odom.v), float(odom.omega)))
        cut = bisect.bisect_left(self._t, self._t[-1] - self.horizon)
        if cut > 0 and len(self._t) - cut >= 2:
            del self._t[:cut], self._pose[:cut], self._vel[:cut]

    def pose_at(self, t: float) -> np.ndarray:
        """Base pose (3,) in the odom frame at time ``t`` (s). Raises LookupError when the buffer is empty."""
        if not self._t:
            raise LookupError("no odometry received yet")
        i = bisect.bisect_right(self._t, t)
        if i == 0:
            return self._pose[0].copy()
        if i == len(self._t):
            p = self._pose[-1]
            v, w = self._vel[-1]
            dt = min(t - self._t[-1], self.max_extrapolation)
            if dt <= 0:
                return p.copy()
            # constant-velocity arc in the base frame
            if abs(w) > 1e-9:
                dx, dy = v / w * np.sin(w * dt), v / w * (1 - np.cos(w * dt))
            else:
                dx, dy = v * dt, 0.0
            return compose(p, np.array([dx, dy, w * dt]))
        t0, t1 = self._t[i - 1], self._t[i]
        p0, p1 = self._pose[i - 1], self._pose[i]
        a = (t - t0) / (t1 - t0)
        yaw = p0[2] + a * float(wrap_angle(p1[2] - p0[2]))
        return np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), float(wrap_angle(yaw))])
