"""Message types shared by the drivers, the core and the runtime.

Units: metres, radians, seconds. Angles counter-clockwise positive; the laser's front beam is at angle 0.
Frames: ``laser`` (sensor), ``base`` (robot), ``odom`` (wheel odometry), ``map`` (world grid).
Times: ``stamp`` fields are host monotonic seconds (``time.monotonic()`` or simulated time); sensor clocks
are kept separately where a device has one.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np


@functools.lru_cache(maxsize=8)
def beam_angles(angle_min: float, angle_increment: float, n: int) -> np.ndarray:
    """``angle_min + angle_increment * arange(n)`` (rad), read-only and shared: a laser sends the same beam
    angles in every scan, so each scan's ``angles`` is the same array object."""
    a = angle_min + angle_increment * np.arange(n)
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class LaserGeometry:
    """Beam layout of a scanning laser (laser frame).

    Beam k points at ``angle_min + k * angle_increment``; ``scan_time`` is the time of one revolution.
    Defaults are the Hokuyo UTM-30LX-EW: 1081 beams, -135..+135 deg in 0.25 deg steps, 25 ms per scan.
    """

    n_beams: int = 1081
    angle_min: float = -3 * np.pi / 4
    angle_increment: float = np.pi / 720
    range_min: float = 0.1
    range_max: float = 30.0
    scan_time: float = 0.025

    @property
    def angles(self) -> np.ndarray:
        """Beam angles in the laser frame (rad), shape (n_beams,), read-only."""
        return beam_angles(self.angle_min, self.angle_increment, self.n_beams)

    @property
    def time_increment(self) -> float:
        """Time between two consecutive beams (s), assuming a 360 deg revolution over scan_time."""
        return self.scan_time * self.angle_increment / (2 * np.pi)


@dataclass
class Scan:
    """One laser scan in the laser frame.

    ranges: metres, shape (n,); NaN = invalid reading, +inf = no return (ROS REP 117).
    intensities: arbitrary sensor units, shape (n,), or None when the sensor did not send them.
    stamp: host time (s) of the first beam. sensor_stamp: the sensor's own clock (s, unwrapped) or None.
    echoes: optional extra echoes (multi-echo), shape (n, e) ranges in metres, NaN where absent.
    """

    stamp: float
    ranges: np.ndarray
    intensities: np.ndarray | None
    geometry: LaserGeometry = field(default_factory=LaserGeometry)
    sensor_stamp: float | None = None
    seq: int = 0
    echoes: np.ndarray | None = None
    echo_intensities: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.ranges = np.asarray(self.ranges, dtype=np.float64)
        if self.ranges.ndim != 1:
            raise ValueError(f"Scan.ranges must be 1-D, got shape {self.ranges.shape}")
        if self.intensities is not None:
            self.intensities = np.asarray(self.intensities, dtype=np.float64)
            if self.intensities.shape != self.ranges.shape:
                raise ValueError(
                    f"Scan.intensities shape {self.intensities.shape} != ranges shape {self.ranges.shape}"
                )

    @property
    def angles(self) -> np.ndarray:
        """Beam angles (rad, laser frame) for the beams in ``ranges``, read-only."""
        g = self.geometry
        return beam_angles(g.angle_min, g.angle_increment, self.ranges.shape[0])


@dataclass
class Odometry:
    """Wheel odometry of the base in the odom frame.

    x, y: metres; yaw: radians in (-pi, pi]; v: m/s forward; omega: rad/s CCW.
    covariance: 3x3 over (x, y, yaw) in the odom frame, accumulated since the first packet.
    stamp: host time (s) of the packet's arrival.
    """

    stamp: float
    x: float
    y: float
    yaw: float
    v: float = 0.0
    omega: float = 0.0
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    @property
    def pose(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw])


@dataclass
class PoseEstimate:
    """Pose of the base in the map frame with its 3x3 covariance over (x, y, yaw) (m^2, rad^2). status: the
    estimator's track, "ok", "degraded" (the last scan match disagreed with the prediction and was not
    used; also after several such matches that disagree with each other: ambiguous, on odometry) or "lost"
    (several in a row that agree: the prediction is wrong until a match relocalises it; do not drive on it)."""

    stamp: float
    x: float
    y: float
    yaw: float
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    status: str = "ok"

    @property
    def pose(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw])

    @property
    def sigma_xy(self) -> float:
        """Position standard deviation (m): sqrt of the larger eigenvalue of the xy covariance block."""
        return float(np.sqrt(max(np.linalg.eigvalsh(self.covariance[:2, :2]).max(), 0.0)))


def wrap_angle(a):
    """Wrap angle(s) to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)
