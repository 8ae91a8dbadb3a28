"""Pioneer 3-DX differential-drive kinematics with noisy wheel odometry, and a waypoint route follower.

Frames: ``map`` (the world; true pose), ``odom`` (what the robot's controller dead-reckons from its wheel
encoders; its origin is the robot's pose when the odometry was started, like XPOS/YPOS/THPOS after power-up),
``base`` (the robot, x forward, y left), ``laser`` (mounted at ``RobotParams.laser_offset`` in ``base``).
Units: metres, radians, seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of the simulated Pioneer 3-DX.

    track: true effective distance between the wheels' contact points (m). The P3-DX controller's
        DiffConvFactor 0.0056 corresponds to 0.357 m.
    max_velocity: largest forward speed the base will run (m/s); max_rot_velocity: largest turn rate (rad/s).
    trans_accel / trans_decel: forward acceleration / deceleration limits (m/s^2; ARIA's default 0.3).
    rot_accel: rotational acceleration limit (rad/s^2; ARIA's default 100 deg/s^2).
    laser_offset: (x, y, yaw) of the laser in the base frame (m, m, rad); the laser's height (about 0.2 m)
        plays no role in 2D.
    max_substep: kinematics are integrated in sub-steps no longer than this (s).
    """

    track: float = 0.357
    max_velocity: float = 0.75
    max_rot_velocity: float = math.radians(100.0)
    trans_accel: float = 0.3
    trans_decel: float = 0.3
    rot_accel: float = math.radians(100.0)
    laser_offset: tuple[float, float, float] = (0.1, 0.0, 0.0)
    max_substep: float = 0.02


@dataclass(frozen=True)
class OdometryNoise:
    """Errors of the wheel odometry (what the encoders and the controller get wrong).

    Each wheel's measured displacement is ``d_true * (1 + scale_error) + slip``, with ``slip`` zero-mean
    Gaussian of variance ``slip_std^2 * |d_true|`` (so the standard deviation grows with the square root of
    the distance, like a random walk); the controller then dead-reckons with a track width of
    ``track * (1 + track_error)``.

    left_scale_error, right_scale_error: systematic relative error of each wheel's measured displacement
        (wheel radius mismatch; a difference between them makes straight lines look curved).
    track_error: relative error of the track width the controller assumes (makes turns over/under-count).
    slip_std: random slip per wheel (m per sqrt(m) of wheel travel).
    """

    left_scale_error: float = 0.002
    right_scale_error: float = 0.0
    track_error: float = 0.02
    slip_std: float = 0.005

    @staticmethod
    def none() -> "OdometryNoise":
        """Perfect odometry."""
        return OdometryNoise(0.0, 0.0, 0.0, 0.0)


def _arc(pose: list[float], ds: float, dth: float) -> None:
    """Move ``pose`` [x, y, yaw] in place by an arc of length ds (m) turning by dth (rad)."""
    x, y, th = pose
    if abs(dth) > 1e-9:
        r = ds / dth
        x += r * (math.sin(th + dth) - math.sin(th))
        y -= r * (math.cos(th + dth) - math.cos(th))
    else:
        x += ds * math.cos(th + dth / 2)
        y += ds * math.sin(th + dth / 2)
    th = math.atan2(math.sin(th + dth), math.cos(th + dth))
    pose[0], pose[1], pose[2] = x, y, th


def _approach(cur: float, target: float, up: float, down: float) -> float:
    """Move ``cur`` toward ``target`` by at most ``up`` when speeding up, ``down`` when slowing down."""
    diff = target - cur
    limit = down if (cur * diff < 0 or target == 0 or abs(target) < abs(cur)) else up
    return cur + max(-limit, min(limit, diff))


class DiffDriveRobot:
    """A P3-DX: set a velocity, step time forward, read the true pose and the noisy odometry.

    pose0: true start pose (x, y, yaw) in the map frame. odom0: the odometry's reading at the start (odom
    frame; default zero, like the controller after power-up). rng: source of the slip noise.
    """

    def __init__(self, params: RobotParams = RobotParams(), noise: OdometryNoise = OdometryNoise(),
                 pose0=(0.0, 0.0, 0.0), rng: np.random.Generator | None = None, odom0=(0.0, 0.0, 0.0)) -> None:
        self.params = params
        self.noise = noise
        self.rng = rng if rng is not None else np.random.default_rng()
        self._true = [float(v) for v in pose0]
        self._odom = [float(v) for v in odom0]
        self._v = 0.0
        self._w = 0.0
        self._cmd = (0.0, 0.0)
        self._wheels = (0.0, 0.0)
        self.time = 0.0
        self.distance = 0.0  # total true distance travelled by the base (m)

    def set_velocity(self, v: float, omega: float) -> None:
        """Command forward speed v (m/s) and turn rate omega (rad/s, CCW +); clamped to the robot's limits."""
        p = self.params
        if not (math.isfinite(v) and math.isfinite(omega)):
            raise ValueError(f"velocity command must be finite, got v={v}, omega={omega}")
        self._cmd = (max(-p.max_velocity, min(p.max_velocity, float(v))),
                     max(-p.max_rot_velocity, min(p.max_rot_velocity, float(omega))))

    def step(self, dt: float) -> None:
        """Advance the true pose and the odometry by dt seconds (acceleration-limited toward the command)."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        p, nz = self.params, self.noise
        n_sub = max(1, math.ceil(dt / p.max_substep - 1e-9))
        h = dt / n_sub
        half = p.track / 2
        track_odom = p.track * (1.0 + nz.track_error)
        dl_sum = dr_sum = 0.0
        for _ in range(n_sub):
            v0, w0 = self._v, self._w
            self._v = _approach(v0, self._cmd[0], p.trans_accel * h, p.trans_decel * h)
            self._w = _approach(w0, self._cmd[1], p.rot_accel * h, p.rot_accel * h)
            v = (v0 + self._v) / 2
            w = (w0 + self._w) / 2
            ds, dth = v * h, w * h
            _arc(self._true, ds, dth)
            self.distance += abs(ds)
            dl, dr = ds - dth * half, ds + dth * half
            if nz.slip_std > 0:
                z = self.rng.standard_normal(2)
                ml = dl * (1 + nz.left_scale_error) + nz.slip_std * math.sqrt(abs(dl)) * z[0]
                mr = dr * (1 + nz.right_scale_error) + nz.slip_std * math.sqrt(abs(dr)) * z[1]
            else:
                ml = dl * (1 + nz.left_scale_error)
                mr = dr * (1 + nz.right_scale_error)
            _arc(self._odom, (ml + mr) / 2, (mr - ml) / track_odom)
            dl_sum += ml
            dr_sum += mr
        self.time += dt
        self._wheels = (dl_sum / dt, dr_sum / dt) if dt > 0 else self._wheels

    @property
    def true_pose(self) -> np.ndarray:
        """(3,) true pose (x, y, yaw) of the base in the map frame."""
        return np.array(self._true)

    @property
    def odom_pose(self) -> np.ndarray:
        """(3,) pose of the base in the odom frame, dead-reckoned from the noisy wheel displacements."""
        return np.array(self._odom)

    @property
    def velocity(self) -> tuple[float, float]:
        """True (v, omega) of the base (m/s, rad/s)."""
        return (self._v, self._w)

    @property
    def command(self) -> tuple[float, float]:
        """The clamped velocity command (v, omega) currently being tracked."""
        return self._cmd

    @property
    def wheel_speeds(self) -> tuple[float, float]:
        """(left, right) wheel speeds (m/s) as the encoders measured them over the last step."""
        return self._wheels

    @property
    def odom_velocity(self) -> tuple[float, float]:
        """(v, omega) computed from the measured wheel speeds with the controller's track width."""
        left, right = self._wheels
        return ((left + right) / 2, (right - left) / (self.params.track * (1 + self.noise.track_error)))

    def laser_pose(self) -> np.ndarray:
        """(3,) true pose (x, y, yaw) of the laser in the map frame."""
        return compose(self.true_pose, np.asarray(self.params.laser_offset, dtype=np.float64))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose composition a (+) b for (..., 3) poses (x, y, yaw): b expressed in a's frame."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = a[..., 2] + b[..., 2]
    return np.stack([x, y, np.arctan2(np.sin(th), np.cos(th))], axis=-1)


class RouteFollower:
    """Drives through waypoints (k, 2) in the map frame, leg by leg, stopping and turning at each corner.

    ``command(pose)`` returns (v, omega) toward a look-ahead point on the current leg; the robot turns in
    place while the heading error exceeds ``turn_in_place`` and slows down before each waypoint so corners
    are not cut. ``done`` becomes True within ``goal_tolerance`` of the last waypoint.
    """

    def __init__(self, waypoints, max_v: float = 0.5, max_omega: float = math.radians(60), *,
                 lookahead: float = 0.4, reach_tolerance: float = 0.1, goal_tolerance: float = 0.08,
                 turn_in_place: float = math.radians(25), heading_gain: float = 2.0, decel: float = 0.25,
                 min_v: float = 0.05) -> None:
        wp = np.asarray(waypoints, dtype=np.float64)
        if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 2:
            raise ValueError(f"waypoints must have shape (k >= 2, 2), got {wp.shape}")
        if max_v <= 0 or max_omega <= 0:
            raise ValueError("max_v and max_omega must be > 0")
        self.waypoints = wp
        self.max_v, self.max_omega = float(max_v), float(max_omega)
        self.lookahead, self.reach_tolerance, self.goal_tolerance = lookahead, reach_tolerance, goal_tolerance
        self.turn_in_place, self.heading_gain, self.decel, self.min_v = turn_in_place, heading_gain, decel, min_v
        self.leg = 0
        self.done = False

    def command(self, pose) -> tuple[float, float]:
        """(v, omega) (m/s, rad/s) for the base at ``pose`` (x, y, yaw) in the map frame."""
        if self.done:
            return 0.0, 0.0
        x, y, yaw = (float(v) for v in pose)
        last = len(self.waypoints) - 1
        while True:
            a, b = self.waypoints[self.leg], self.waypoints[self.leg + 1]
            ab = b - a
            length = float(np.hypot(*ab))
            s = float(np.dot([x - a[0], y - a[1]], ab) / max(length, 1e-9))
            dist_b = math.hypot(b[0] - x, b[1] - y)
            if self.leg + 1 == last:
                if dist_b < self.goal_tolerance:
                    self.done = True
                    return 0.0, 0.0
                break
            if dist_b < self.reach_tolerance or s >= length:
                self.leg += 1
                continue
            break
        s_t = min(max(s, 0.0) + self.lookahead, length)
        target = a + ab * (s_t / max(length, 1e-9))
        if math.hypot(target[0] - x, target[1] - y) < 1e-6:
            target = b
        err = math.atan2(target[1] - y, target[0] - x) - yaw
        err = math.atan2(math.sin(err), math.cos(err))
        omega = max(-self.max_omega, min(self.max_omega, self.heading_gain * err))
        if abs(err) > self.turn_in_place:
            return 0.0, omega
        v = self.max_v * math.cos(err)
        v = min(v, math.sqrt(2 * self.decel * dist_b), self.max_v * (1 - abs(omega) / self.max_omega / 2))
        return max(v, self.min_v), omega
