"""Wheel odometry: a time-ordered buffer interpolated to scan times, SE(2) helpers and the motion-noise model.

Frames: odometry poses are the base in the ``odom`` frame; relative motions are expressed in the base frame
at the start of the motion. Units: metres, radians, seconds.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from glassmap.pose.filter_jit import compose_covariance as _compose_covariance, motion_covariance
from glassmap.types import Odometry


_TWO_PI = 2 * math.pi


def _wrap(a: float) -> float:
    """:func:`~glassmap.types.wrap_angle` of one float (rad): the same operations on Python floats (float
    ``%`` is numpy's ``np.mod``: fmod, then the divisor's sign), so the same value to the last bit."""
    return math.pi - (math.pi - a) % _TWO_PI


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) composition a (+) b: pose b given in the frame of pose a, expressed in a's parent frame."""
    ax, ay, at = float(a[0]), float(a[1]), float(a[2])
    bx, by, bt = float(b[0]), float(b[1]), float(b[2])
    c, s = math.cos(at), math.sin(at)
    return np.array([ax + c * bx - s * by, ay + s * bx + c * by, _wrap(at + bt)])


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of b in the frame of a (a^-1 (+) b), so that compose(a, relative(a, b)) == b."""
    ax, ay, at = float(a[0]), float(a[1]), float(a[2])
    c, s = math.cos(at), math.sin(at)
    dx, dy = float(b[0]) - ax, float(b[1]) - ay
    return np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(float(b[2]) - at)])


def points_to_map(pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points ``pts`` (n, 2) in the frame of ``pose`` (3,) as map-frame points (n, 2), m."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return pose[:2] + pts @ np.array([[c, s], [-s, c]])


def compose_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (3x3, 3x3) of compose(a, b) with respect to a and to b."""
    at, bx, by = float(a[2]), float(b[0]), float(b[1])
    c, s = math.cos(at), math.sin(at)
    ja = np.array([[1.0, 0.0, -s * bx - c * by],
                   [0.0, 1.0, c * bx - s * by],
                   [0.0, 0.0, 1.0]])
    jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja, jb


def compose_covariance(a: np.ndarray, b: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """Covariance (3, 3, symmetric) of ``compose(a, b)`` for a pose a (3,) of covariance cov_a (a's parent
    frame) and a relative pose b (3,) of independent covariance cov_b (a's frame): first order, with the
    Jacobians of :func:`compose_jacobians` (one compiled step, :func:`glassmap.pose.filter_jit.compose_covariance`)."""
    f64 = np.float64
    return _compose_covariance(np.asarray(a, dtype=f64), np.asarray(b, dtype=f64), np.asarray(cov_a, dtype=f64),
                               np.asarray(cov_b, dtype=f64))


@dataclass(frozen=True)
class MotionNoise:
    """Noise of one relative odometry motion (dx, dy, dyaw) in the base frame, as standard deviations.

    For a motion of translation d (m) and rotation |dyaw| (rad) lasting dt (s), the covariance is diagonal
    in the base frame with

        var_along = (trans_per_m * d)^2 + trans_rw * d + (xy_per_s^2) * dt
        var_lateral = (lateral_per_m * d)^2 + trans_rw * d + (xy_per_s^2) * dt
        var_yaw = (rot_per_rad * |dyaw|)^2 + (rot_per_m * d)^2 + rot_rw_m * d + rot_rw_rad * |dyaw|
                  + (yaw_per_s^2) * dt

    Extrapolation past the newest odometry message adds a transient term, see
    :meth:`extrapolation_covariance`.

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
    extrapolation_v: float = 0.02  # m/s
    extrapolation_omega: float = 0.1  # rad/s

    def extrapolation_covariance(self, v: float, dt: float, omega: float = 0.0, held: float = 0.0) -> np.ndarray:
        """3x3 covariance (base frame) of a pose extrapolated ``dt`` seconds past the newest odometry with its
        velocity (v m/s forward, omega rad/s): the velocity a wheel-odometry message carries is measured over
        a short interval and is noisy (``extrapolation_v``, ``extrapolation_omega``: 1-sigma; the defaults are
        the simulated P3-DX's slip noise seen over one 25 ms step at 0.5 m/s, 0.09 rad/s). A yaw-rate error
        d_omega turns the pose by d_omega dt and moves it sideways by v d_omega dt^2 / 2. ``held``: seconds
        beyond the extrapolation limit, when the pose is held although the base may still be moving at up to
        its last velocity (odometry late, e.g. under CPU load): (|v| + extrapolation_v) held along the track
        and (|omega| + extrapolation_omega) held in yaw. The error is transient: the next odometry message
        replaces the extrapolation (see ``PoseEstimator.covariance``)."""
        dt, held = max(float(dt), 0.0), max(float(held), 0.0)
        sv, sw = self.extrapolation_v * dt, self.extrapolation_omega * dt
        lat = 0.5 * abs(float(v)) * dt * sw
        out = np.array([[sv * sv, 0.0, 0.0], [0.0, lat * lat, lat * sw], [0.0, lat * sw, sw * sw]])
        if held > 0:
            out[0, 0] += ((abs(float(v)) + self.extrapolation_v) * held) ** 2
            out[2, 2] += ((abs(float(omega)) + self.extrapolation_omega) * held) ** 2
        return out

    def covariance(self, delta: np.ndarray, dt: float) -> np.ndarray:
        """3x3 covariance of the relative motion ``delta`` (base frame at the start) over ``dt`` seconds."""
        d = float(np.hypot(delta[0], delta[1]))
        r = abs(float(delta[2]))
        dt = max(float(dt), 0.0)
        var_along = (self.trans_per_m * d) ** 2 + self.trans_rw * d + self.xy_per_s ** 2 * dt
        var_lat = (self.lateral_per_m * d) ** 2 + self.trans_rw * d + self.xy_per_s ** 2 * dt
        var_yaw = ((self.rot_per_rad * r) ** 2 + (self.rot_per_m * d) ** 2 + self.rot_rw_m * d
                   + self.rot_rw_rad * r + self.yaw_per_s ** 2 * dt)
        # along / lateral axes follow the direction of travel: rot diag(along, lat) rot^T
        return motion_covariance(float(delta[0]), float(delta[1]), d, var_along, var_lat, var_yaw)


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
    def newest(self) -> float | None:
        """Stamp (s) of the newest message, None when the buffer is empty."""
        return self._t[-1] if self._t else None

    def extrapolation(self, t: float) -> tuple[float, float, float, float]:
        """(seconds past the newest message that :meth:`pose_at` extrapolates for time ``t``, clipped to
        ``max_extrapolation``; the newest forward velocity, m/s; its yaw rate, rad/s; seconds beyond the
        clip, during which the pose is held). (0, 0, 0, 0) when t is inside the buffer."""
        if not self._t or t <= self._t[-1]:
            return 0.0, 0.0, 0.0, 0.0
        past = t - self._t[-1]
        v, w = self._vel[-1]
        return min(past, self.max_extrapolation), v, w, max(past - self.max_extrapolation, 0.0)

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
        (x0, y0, th0), (x1, y1, th1) = self._pose[i - 1].tolist(), self._pose[i].tolist()
        a = (t - t0) / (t1 - t0)
        yaw = th0 + a * _wrap(th1 - th0)
        return np.array([x0 + a * (x1 - x0), y0 + a * (y1 - y0), _wrap(yaw)])


def deskew(angles: np.ndarray, ranges: np.ndarray, mount: np.ndarray, delta: np.ndarray,
           fraction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undo the base's motion during a laser sweep (vectorized, no per-beam loop).

    A scanning laser takes beam k at ``stamp + k * time_increment``; while it sweeps (about 19 ms for the
    UTM-30LX's 270 deg) the base keeps moving, so a scan taken while turning at 60 deg/s is bent by up to
    1.1 deg. ``delta`` (3,) is the base motion over the whole sweep (base frame at the first beam, e.g. from
    odometry), ``fraction`` (n,) how far through the sweep each beam was taken (0 .. 1); the base pose at beam
    k is taken as ``fraction[k] * delta`` (constant twist, to first order). Returns (angles, ranges) of the
    same end points seen from the laser at the first beam's time (laser frame; NaN / inf ranges unchanged).
    """
    angles = np.asarray(angles, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    fraction = np.asarray(fraction, dtype=np.float64)
    finite = np.isfinite(ranges)
    r = np.where(finite, ranges, 0.0)
    mc, ms = np.cos(mount[2]), np.sin(mount[2])
    # end point in the base frame at the beam's own time
    la = mount[2] + angles
    bx, by = mount[0] + r * np.cos(la), mount[1] + r * np.sin(la)
    # moved by the base's motion up to that beam
    dx, dy, dth = fraction * delta[0], fraction * delta[1], fraction * delta[2]
    c, s = np.cos(dth), np.sin(dth)
    qx, qy = dx + c * bx - s * by, dy + s * bx + c * by
    # back into the laser frame at the first beam
    lx, ly = qx - mount[0], qy - mount[1]
    ex, ey = mc * lx + ms * ly, -ms * lx + mc * ly
    out_r = np.where(finite, np.hypot(ex, ey), ranges)
    out_a = np.where(finite, np.arctan2(ey, ex), angles)
    return out_a, out_r
