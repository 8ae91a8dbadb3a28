"""Pioneer odometry: conversion factors, 15-bit unwrapping, and a covariance model (sans-IO).

The controller dead-reckons and reports XPOS/YPOS (only 15 bits valid: a real robot wraps at 0x8000, a
simulator at 0x10000; masking with 0x7FFF serves both) and THPOS (4096 units per turn). The tracker takes
the delta of each field to the previous SIP, brings it into the nearest equivalent value (modulo 0x8000
for positions, modulo 4096 for the heading: a step of up to +-16383 units, e.g. 7.9 m per SIP on a p3dx,
is followed, so large real steps are never discarded), scales it and accumulates it.

The first SIP anchors the pose: its 15-bit positions read as signed 15-bit values and its heading as an
absolute angle, so a robot whose controller odometry is within +-0x4000 units of zero (7.9 m for a p3dx,
16.4 m for a p3dx-sh) starts at the controller's own pose; use SETO to start from zero.

Plausibility: a step larger than the robot can drive between two SIPs (``max_v`` and ``max_omega`` over the
host time between them, plus a few units of quantisation) is physically impossible: a corrupted SIP that
passed the 16-bit checksum. It is not integrated (the pose stays continuous), counted in ``rejected_steps``
and logged. If ``reanchor_after`` consecutive SIPs all disagree with the last accepted one but agree with
each other, the controller's odometry really jumped (a reset, SETO by another client): the tracker
re-anchors on them without moving the pose.

Covariance (odom frame, over x, y, yaw): a wheel model. Each SIP step (distance d, rotation a) is split into
left and right wheel travel dL = d - a T / 2, dR = d + a T / 2 (T: the track width of the model) with

- random slip per wheel: variance ``slip**2 * |dL|`` and ``slip**2 * |dR|`` (m^2), independent;
- systematic errors, constant for a robot: relative scale errors eps_L, eps_R of the wheels (standard
  deviation ``scale_sigma``) and a relative error eps_T of the track width the controller assumes
  (``track_sigma``). They are unknown, so they are states of the error model (an augmented 6 x 6
  covariance over x, y, yaw, eps_L, eps_R, eps_T): their effect on consecutive steps is fully correlated,
  so a track-width error makes the heading error grow linearly with the angle turned, not with its root.

The step's distance error is (dL eps_L + dR eps_R + nL + nR) / 2, its rotation error
(dR eps_R - dL eps_L + nR - nL) / T - a eps_T, propagated through the motion model (x += d cos(yaw_mid),
y += d sin(yaw_mid), yaw += a) with its Jacobians. The reported covariance is the (x, y, yaw) block. At
rest it does not grow. The densities are those of a P3-DX's documented odometry error magnitudes; calibrate
them for a given robot (e.g. UMBmark square runs) and set them in ``CovarianceModel``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from glassmap.types import Odometry, wrap_angle

from drivers.pioneer.errors import UnsupportedRobotError
from drivers.pioneer.sip import StandardSIP

log = logging.getLogger(__name__)

POS_MODULO = 0x8000
POS_MASK = 0x7FFF
HEADING_UNITS = 4096
MIN_TURN_PER_CYCLE = 0.02  # rad: slower turns cannot tell cycles apart from a SIP's content (cycles_since_last)
MIN_MOVE_PER_CYCLE = 0.01  # m: the same for driving straight


@dataclass(frozen=True)
class PioneerModel:
    """Conversion factors of one robot subclass.

    dist_conv: mm per XPOS/YPOS unit. angle_conv: rad per THPOS unit. diff_conv: rad/s per mm/s of
    (vR - vL) / 2. vel_conv: mm/s per LVEL/RVEL unit. vel2_divisor: mm/s per VEL2 unit.
    max_v: m/s and max_omega: rad/s the controller accepts.
    """

    subclass: str
    dist_conv: float
    angle_conv: float = 0.001534
    diff_conv: float = 0.0056
    vel_conv: float = 1.0
    vel2_divisor: float = 20.0
    range_conv: float = 1.0
    max_v: float = 2.2
    max_omega: float = math.radians(500.0)
    radius: float = 0.25


MODELS: dict[str, PioneerModel] = {
    "p3dx": PioneerModel("p3dx", dist_conv=0.485),
    "p3dx-sh": PioneerModel("p3dx-sh", dist_conv=1.0),
}


def model_for(subclass: str, robot_class: str = "Pioneer") -> PioneerModel:
    """Conversion factors for a reported subclass (case-insensitive). Raises UnsupportedRobotError."""
    key = subclass.strip().lower()
    if key in MODELS:
        return MODELS[key]
    raise UnsupportedRobotError(
        f"robot reports class {robot_class!r} subclass {subclass!r}; this driver knows {sorted(MODELS)}. "
        "If it is a P3-DX with another name, pass model='p3dx' (old controller, 0.485 mm/unit) or "
        "model='p3dx-sh' (1 mm/unit) to the client")


@dataclass(frozen=True)
class CovarianceModel:
    """Odometry error model (see module docstring).

    slip: random wheel slip, m per sqrt(m) of wheel travel. scale_sigma: standard deviation of each wheel's
    relative scale error (wheel radius). track_sigma: standard deviation of the relative error of the track
    width the controller dead-reckons with. slack_units: quantisation allowance (position units) of the
    plausibility check. reanchor_after: consecutive implausible but mutually consistent SIPs after which
    the tracker re-anchors.
    """

    slip: float = 0.005
    scale_sigma: float = 0.003
    track_sigma: float = 0.02
    slack_units: int = 4
    reanchor_after: int = 3


def _nearest(delta: int, modulo: int) -> int:
    """Bring a raw delta into [-modulo/2, modulo/2)."""
    half = modulo // 2
    return (delta + half) % modulo - half


def pose_to_units(x: float, y: float, yaw: float, model: PioneerModel, position_bits: int = 15) -> tuple[int, int, int]:
    """A controller pose (odom frame, m and rad) as SIP XPOS, YPOS (masked to ``position_bits``) and THPOS."""
    mask = (1 << position_bits) - 1
    xu = int(round(x * 1000.0 / model.dist_conv)) & mask
    yu = int(round(y * 1000.0 / model.dist_conv)) & mask
    thu = (int(round(yaw / model.angle_conv)) + HEADING_UNITS // 2) % HEADING_UNITS - HEADING_UNITS // 2
    return xu, yu, thu


def signed15(value: int) -> int:
    """A masked 15-bit position read as a signed 15-bit value."""
    v = value & POS_MASK
    return v - POS_MODULO if v >= POS_MODULO // 2 else v


class OdometryTracker:
    """Turns a stream of SIPs into odometry poses (m, rad, odom frame) with a growing covariance.

    time_scale: > 1 for a robot (emulator) running that many times faster than the host clock: velocities
    are then reported per host second, like the stamps (anything that extrapolates with them needs that).
    """

    def __init__(self, model: PioneerModel, noise: CovarianceModel = CovarianceModel(),
                 time_scale: float = 1.0) -> None:
        self.model = model
        self.noise = noise
        self.time_scale = float(time_scale)
        self.track = 2.0 / (model.diff_conv * 1000.0)  # m: rad/s = diff_conv * (vR - vL) / 2 in mm/s
        self._raw: tuple[int, int, int] | None = None
        self._stamp: float | None = None
        self._suspects: list[tuple[int, int, int]] = []
        self.x = self.y = 0.0  # metres
        self.yaw_unwrapped = 0.0  # radians, not wrapped (total turn + initial heading)
        self._cov = np.zeros((6, 6))  # x, y, yaw, eps_L, eps_R, eps_T
        self._cov[3:, 3:] = np.diag([noise.scale_sigma ** 2, noise.scale_sigma ** 2, noise.track_sigma ** 2])
        self.distance = 0.0  # m travelled (absolute)
        self.rotation = 0.0  # rad turned (absolute)
        self.max_step_units = 0  # largest accepted position step (units), for diagnostics
        self.rejected_steps = 0  # SIPs not integrated: a step the robot cannot have made
        self.reanchors = 0  # controller odometry jumps followed by re-anchoring

    @property
    def covariance(self) -> np.ndarray:
        """(3, 3) covariance of (x, y, yaw) in the odom frame (m^2, rad^2)."""
        return self._cov[:3, :3].copy()

    def reanchor(self) -> None:
        """Forget the last raw values: the next SIP anchors again (after SETO resets the controller)."""
        self._raw = None

    def update(self, sip: StandardSIP, stamp: float) -> Odometry:
        """Integrate one SIP received at host time ``stamp`` (s) and return the odometry."""
        m = self.model
        raw = (sip.xpos & POS_MASK, sip.ypos & POS_MASK, sip.thpos)
        if self._raw is None:
            self.x = signed15(raw[0]) * m.dist_conv / 1000.0
            self.y = signed15(raw[1]) * m.dist_conv / 1000.0
            self.yaw_unwrapped = float(wrap_angle(_nearest(raw[2], HEADING_UNITS) * m.angle_conv))
            self._raw = raw
        else:
            steps = self._steps(self._raw, raw)
            if self._plausible(steps, stamp):
                self._suspects.clear()
                self._integrate(*steps)
                self._raw = raw
            else:
                self._reject(raw, steps)
        self._stamp = stamp
        v = (sip.lvel + sip.rvel) / 2.0 * m.vel_conv / 1000.0 * self.time_scale
        omega = (sip.rvel - sip.lvel) / 2.0 * m.vel_conv * m.diff_conv * self.time_scale
        return Odometry(stamp=stamp, x=self.x, y=self.y, yaw=float(wrap_angle(self.yaw_unwrapped)), v=v,
                        omega=omega, covariance=self.covariance)

    def cycles_since_last(self, sip: StandardSIP, cycle: float) -> float | None:
        """How many SIP cycles of ``cycle`` robot seconds ``sip`` moves the robot on since the last SIP
        integrated: its turn (or, driving straight, its distance) over its wheel speeds (the encoders' over
        the cycle it reports) times the cycle. None before the first SIP, or when the robot turns less than
        0.02 rad and moves less than 1 cm per cycle (too slow to tell)."""
        if self._raw is None or cycle <= 0:
            return None
        m = self.model
        dx, dy, dth = self._steps(self._raw, (sip.xpos & POS_MASK, sip.ypos & POS_MASK, sip.thpos))
        left, right = float(sip.lvel), float(sip.rvel)
        turn = abs(right - left) / 2.0 * m.vel_conv * m.diff_conv * cycle  # rad per cycle
        move = abs(left + right) / 2.0 * m.vel_conv / 1000.0 * cycle  # m per cycle
        if turn >= MIN_TURN_PER_CYCLE:
            return abs(dth) * m.angle_conv / turn
        if move >= MIN_MOVE_PER_CYCLE:
            return math.hypot(dx, dy) * m.dist_conv / 1000.0 / move
        return None

    @staticmethod
    def _steps(a: tuple[int, int, int], b: tuple[int, int, int]) -> tuple[int, int, int]:
        return _nearest(b[0] - a[0], POS_MODULO), _nearest(b[1] - a[1], POS_MODULO), _nearest(b[2] - a[2], HEADING_UNITS)

    def _plausible(self, steps: tuple[int, int, int], stamp: float) -> bool:
        m = self.model
        dt = max(stamp - self._stamp, 0.0) * self.time_scale if self._stamp is not None else 0.0
        dt = max(dt, 0.1)  # at least one SIP period: stamps of a burst of buffered SIPs are close together
        slack = self.noise.slack_units
        max_units = m.max_v * dt * 1000.0 / m.dist_conv + slack
        max_heading = m.max_omega * dt / m.angle_conv + slack
        return math.hypot(steps[0], steps[1]) <= max_units and abs(steps[2]) <= max_heading

    def _reject(self, raw: tuple[int, int, int], steps: tuple[int, int, int]) -> None:
        m = self.model
        self.rejected_steps += 1
        log.warning("odometry: implausible step (%.2f m, %.0f deg in one SIP) not integrated; %d so far",
                    math.hypot(steps[0], steps[1]) * m.dist_conv / 1000.0, math.degrees(steps[2] * m.angle_conv),
                    self.rejected_steps)
        if self._suspects and not all(abs(d) <= self.noise.slack_units * 10
                                      for d in self._steps(self._suspects[-1], raw)):
            self._suspects.clear()
        self._suspects.append(raw)
        if len(self._suspects) >= self.noise.reanchor_after:
            log.warning("odometry: the controller's pose jumped and stayed (%d SIPs agree): re-anchored, the "
                        "odometry pose continues from where it was", len(self._suspects))
            self.reanchors += 1
            self._raw = raw
            self._suspects.clear()

    def _integrate(self, dxu: int, dyu: int, dthu: int) -> None:
        m = self.model
        self.max_step_units = max(self.max_step_units, abs(dxu), abs(dyu))
        dx, dy = dxu * m.dist_conv / 1000.0, dyu * m.dist_conv / 1000.0
        da = dthu * m.angle_conv
        self._propagate(dx, dy, da)
        self.x += dx
        self.y += dy
        self.yaw_unwrapped += da

    def _propagate(self, dx: float, dy: float, da: float) -> None:
        d = math.hypot(dx, dy)
        yaw0 = self.yaw_unwrapped
        # Direction of travel: the controller's xy step; reversing shows as a step against the heading.
        heading_mid = yaw0 + da / 2.0
        if d > 0 and math.cos(math.atan2(dy, dx) - heading_mid) < 0:
            d = -d
        self.distance += abs(d)
        self.rotation += abs(da)
        c, s = math.cos(heading_mid), math.sin(heading_mid)
        t = self.track
        dl, dr = d - da * t / 2.0, d + da * t / 2.0
        # (distance, rotation) errors of the step -> pose errors
        g = np.array([[c, -d * s / 2.0], [s, d * c / 2.0], [0.0, 1.0]])
        sys_ = g @ np.array([[dl / 2.0, dr / 2.0, 0.0], [-dl / t, dr / t, -da]])  # per eps_L, eps_R, eps_T
        rnd = g @ np.array([[0.5, 0.5], [-1.0 / t, 1.0 / t]])  # per wheel slip nL, nR
        a = np.eye(6)
        a[0, 2], a[1, 2] = -d * s, d * c
        a[:3, 3:] = sys_
        q = np.diag([abs(dl), abs(dr)]) * self.noise.slip ** 2
        self._cov = a @ self._cov @ a.T
        self._cov[:3, :3] += rnd @ q @ rnd.T
