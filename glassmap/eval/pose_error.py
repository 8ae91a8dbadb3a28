"""Pose-error model of the experiment: the estimated pose is the true pose plus a time-correlated error.

Each component (x, y in metres, yaw in radians) is an independent first-order Gauss-Markov (AR(1)) process
with stationary standard deviation sigma_xy (x and y each) or sigma_theta (yaw) and correlation time tau (s):
e_k = a e_{k-1} + sqrt(1 - a^2) sigma n_k, a = exp(-dt / tau), n_k ~ N(0, 1), e_0 ~ N(0, sigma^2).
A scan-matching SLAM drifts slowly and corrects now and then, which this reproduces; tau = 0 gives white
noise. Registration is told the same sigmas (docs/method.md eq. 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoseErrorModel:
    """sigma_xy: m per axis; sigma_theta: rad; tau: correlation time (s), 0 = independent per scan."""

    sigma_xy: float = 0.05
    sigma_theta: float = np.radians(0.25)
    tau: float = 2.0

    def __post_init__(self) -> None:
        if self.sigma_xy < 0 or self.sigma_theta < 0 or self.tau < 0:
            raise ValueError("sigma_xy, sigma_theta and tau must be >= 0")

    def sample(self, stamps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Errors (k, 3) (dx m, dy m, dyaw rad) at the times ``stamps`` (k,) s, increasing."""
        t = np.asarray(stamps, dtype=np.float64)
        k = t.shape[0]
        sig = np.array([self.sigma_xy, self.sigma_xy, self.sigma_theta])
        noise = rng.standard_normal((k, 3))
        e = np.empty((k, 3))
        if k == 0:
            return e
        e[0] = noise[0] * sig
        if self.tau <= 0:
            return noise * sig
        a = np.exp(-np.diff(t) / self.tau)
        b = np.sqrt(1.0 - a * a)
        for i in range(1, k):  # one step per scan, not per beam
            e[i] = a[i - 1] * e[i - 1] + b[i - 1] * sig * noise[i]
        return e

    def beam_sigma(self, ranges: np.ndarray) -> np.ndarray:
        """End-point sigma (m) per beam: sqrt(sigma_xy^2 + (r sigma_theta)^2); NaN ranges give sigma_xy."""
        r = np.nan_to_num(np.asarray(ranges, dtype=np.float64), nan=0.0, posinf=0.0)
        return np.sqrt(self.sigma_xy ** 2 + (r * self.sigma_theta) ** 2)
