"""Pioneer odometry: conversion factors, 15-bit unwrapping, and a covariance model (sans-IO).

The controller dead-reckons and reports XPOS/YPOS (only 15 bits valid: a real robot wraps at 0x8000, a
simulator at 0x10000; masking with 0x7FFF serves both) and THPOS (4096 units per turn). The tracker takes
the delta of each field to the previous SIP, brings it into the nearest equivalent value (modulo 0x8000
for positions, modulo 4096 for the heading: a step of up to +-16383 units, e.g. 7.9 m per SIP on a p3dx,
is followed, so large real steps are never discarded), scales it and accumulates it.

The first SIP anchors the pose: its 15-bit positions read as signed 15-bit values and its heading as an
absolute angle, so a robot whose controller odometry is within +-0x4000 units of zero (7.9 m for a p3dx,
16.4 m for a p3dx-sh) starts at the controller's own pose; use SETO to start from zero.

Covariance (odom frame, over x, y, yaw): each SIP step of travelled distance ``d`` (m) and rotation ``a``
(rad) adds independent errors with variances

    var_d   = k_d**2 * |d|                      (distance error, m^2)
    var_l   = k_l**2 * |d|                      (lateral error, m^2)
    var_yaw = k_a**2 * |a| + k_ad**2 * |d|      (heading error from turning and from driving, rad^2)

propagated through the motion model (x += d cos(yaw_mid), y += d sin(yaw_mid), yaw += a) with its
Jacobians. A robot that stands still keeps its covariance; it grows with distance and with turning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from glassmap.types import Odometry, wrap_angle

from drivers.pioneer.errors import UnsupportedRobotError
from drivers.pioneer.sip import StandardSIP

POS_MODULO = 0x8000
POS_MASK = 0x7FFF
HEADING_UNITS = 4096


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
    """Odometry noise densities (see module docstring).

    k_d: m per sqrt(m) travelled (distance error); k_l: m per sqrt(m) (lateral error);
    k_a: rad per sqrt(rad) turned; k_ad: rad per sqrt(m) travelled (heading drift while driving).
    Defaults: about 3 cm and 4 deg of 1-sigma error after 1 m straight, 4 deg after a full turn in place.
    """

    k_d: float = 0.03
    k_l: float = 0.015
    k_a: float = 0.03
    k_ad: float = 0.07


def _nearest(delta: int, modulo: int) -> int:
    """Bring a raw delta into [-modulo/2, modulo/2)."""
    half = modulo // 2
    return (delta + half) % modulo - half


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
        self._raw: tuple[int, int, int] | None = None
        self.x = self.y = 0.0  # metres
        self.yaw_unwrapped = 0.0  # radians, not wrapped (total turn + initial heading)
        self.covariance = np.zeros((3, 3))
        self.distance = 0.0  # m travelled (absolute)
        self.rotation = 0.0  # rad turned (absolute)
        self.max_step_units = 0  # largest position step seen (units), for diagnostics

    def reanchor(self) -> None:
        """Forget the last raw values: the next SIP anchors again (after SETO resets the controller)."""
        self._raw = None

    def update(self, sip: StandardSIP, stamp: float) -> Odometry:
        """Integrate one SIP received at host time ``stamp`` (s) and return the odometry."""
        m = self.model
        rx, ry, rth = sip.xpos & POS_MASK, sip.ypos & POS_MASK, sip.thpos
        if self._raw is None:
            self.x = signed15(rx) * m.dist_conv / 1000.0
            self.y = signed15(ry) * m.dist_conv / 1000.0
            self.yaw_unwrapped = float(wrap_angle(_nearest(rth, HEADING_UNITS) * m.angle_conv))
        else:
            px, py, pth = self._raw
            dxu, dyu = _nearest(rx - px, POS_MODULO), _nearest(ry - py, POS_MODULO)
            dthu = _nearest(rth - pth, HEADING_UNITS)
            self.max_step_units = max(self.max_step_units, abs(dxu), abs(dyu))
            dx, dy = dxu * m.dist_conv / 1000.0, dyu * m.dist_conv / 1000.0
            da = dthu * m.angle_conv
            self._propagate(dx, dy, da)
            self.x += dx
            self.y += dy
            self.yaw_unwrapped += da
        self._raw = (rx, ry, rth)
        v = (sip.lvel + sip.rvel) / 2.0 * m.vel_conv / 1000.0 * self.time_scale
        omega = (sip.rvel - sip.lvel) / 2.0 * m.vel_conv * m.diff_conv * self.time_scale
        return Odometry(stamp=stamp, x=self.x, y=self.y, yaw=float(wrap_angle(self.yaw_unwrapped)), v=v,
                        omega=omega, covariance=self.covariance.copy())

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
        f = np.array([[1.0, 0.0, -d * s], [0.0, 1.0, d * c], [0.0, 0.0, 1.0]])
        # Noise inputs: (distance, lateral, yaw) errors.
        g = np.array([[c, -s, -d * s / 2.0], [s, c, d * c / 2.0], [0.0, 0.0, 1.0]])
        n = self.noise
        q = np.diag([n.k_d ** 2 * abs(d), n.k_l ** 2 * abs(d), n.k_a ** 2 * abs(da) + n.k_ad ** 2 * abs(d)])
        self.covariance = f @ self.covariance @ f.T + g @ q @ g.T
