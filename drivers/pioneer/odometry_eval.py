"""Consistency of the odometry covariance against the emulator's robot: drive a scripted motion with the
simulated P3-DX (its wheel slip, wheel-scale and track-width errors), feed its SIPs (quantised as the
emulator sends them) through :class:`OdometryTracker`, and compare the tracker's error at the end with its
reported covariance (NEES, 3 dof: x, y, yaw in the odom frame) over many seeds.

Two kinds of robot: ``"emulator"``, the emulator's default robot (fixed systematic errors, only the slip
random per seed), and ``"drawn"``, a robot per seed whose systematic errors are drawn from the covariance
model's own prior (a fleet of robots: the NEES then follows the chi-square distribution if the model is
consistent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.pioneer.odometry import MODELS, CovarianceModel, OdometryTracker, pose_to_units
from drivers.pioneer.sip import StandardSIP

CHI2_3DOF_95 = 7.815
SIP_PERIOD = 0.1  # s
MOTIONS = {"straight": (0.4, 0.0, 5.0), "turn": (0.0, math.radians(60.0), 6.0)}  # v m/s, omega rad/s, seconds


@dataclass(frozen=True)
class OdometryConsistency:
    """NEES of one motion and kind of robot over the seeds."""

    motion: str
    robot: str
    seeds: int
    nees_mean: float
    inside_95: float  # share of seeds with NEES below the chi-square(3) 95 % point
    error_rms: tuple[float, float, float]  # x, y (m), yaw (rad)
    sigma_rms: tuple[float, float, float]  # reported standard deviations, same units


def _robot(kind: str, seed: int, noise: CovarianceModel):
    from glassmap.sim.robot import DiffDriveRobot, OdometryNoise

    rng = np.random.default_rng(seed)
    if kind == "emulator":
        return DiffDriveRobot(noise=OdometryNoise(), rng=rng)
    if kind == "drawn":
        e = rng.standard_normal(3)
        return DiffDriveRobot(noise=OdometryNoise(left_scale_error=noise.scale_sigma * e[0],
                                                  right_scale_error=noise.scale_sigma * e[1],
                                                  track_error=noise.track_sigma * e[2], slip_std=noise.slip),
                              rng=rng)
    raise ValueError(f"unknown robot kind {kind!r}: 'emulator' or 'drawn'")


def run_motion(motion: str, robot_kind: str, seed: int, noise: CovarianceModel = CovarianceModel(),
               subclass: str = "p3dx-sh") -> tuple[np.ndarray, np.ndarray]:
    """One run: (error (3,) of the tracker's final pose against the truth, reported covariance (3, 3))."""
    v, w, duration = MOTIONS[motion]
    model = MODELS[subclass]
    robot = _robot(robot_kind, seed, noise)
    tracker = OdometryTracker(model, noise)
    t = 0.0
    steps = int(round((duration + 2.0) / SIP_PERIOD))  # the motion, then 2 s to come to rest
    for k in range(steps + 1):
        if k:
            robot.set_velocity(*((v, w) if t < duration else (0.0, 0.0)))
            robot.step(SIP_PERIOD)
            t += SIP_PERIOD
        xu, yu, thu = pose_to_units(*robot.odom_pose, model)
        odom = tracker.update(StandardSIP(False, xu, yu, thu, 0, 0, 120), t)
    truth = robot.true_pose
    err = np.array([odom.x - truth[0], odom.y - truth[1], math.remainder(odom.yaw - truth[2], 2 * math.pi)])
    return err, odom.covariance


def evaluate(motion: str, robot_kind: str, seeds: list[int], noise: CovarianceModel = CovarianceModel()
             ) -> OdometryConsistency:
    errs, nees, sig = [], [], []
    for s in seeds:
        e, p = run_motion(motion, robot_kind, s, noise)
        errs.append(e)
        sig.append(np.sqrt(np.diag(p)))
        nees.append(float(e @ np.linalg.solve(p, e)))
    errs, nees, sig = np.array(errs), np.array(nees), np.array(sig)
    rms = lambda a: tuple(float(x) for x in np.sqrt(np.mean(a ** 2, axis=0)))  # noqa: E731
    return OdometryConsistency(motion, robot_kind, len(seeds), float(nees.mean()),
                               float(np.mean(nees <= CHI2_3DOF_95)), rms(errs), rms(sig))


def format_result(r: OdometryConsistency) -> str:
    ex, ey, eth = r.error_rms
    sx, sy, sth = r.sigma_rms
    return (f"{r.motion:8s} {r.robot:8s} seeds {r.seeds}: mean NEES {r.nees_mean:5.2f} (3 dof, ideal 3), "
            f"{100 * r.inside_95:3.0f} % inside the 95 % bound; error rms x {100 * ex:.1f} cm, y {100 * ey:.1f} cm, "
            f"yaw {math.degrees(eth):.2f} deg; reported sigma x {100 * sx:.1f} cm, y {100 * sy:.1f} cm, "
            f"yaw {math.degrees(sth):.2f} deg")
