"""Maps that follow the pose graph: the key scans re-integrated at their optimised poses.

The occupancy grid gets every key scan at its optimised laser pose. Key scans that carry their raw scan
and p(glass) per beam (:class:`~glassmap.pose.keyscan.KeyScan` ``scan`` / ``p_glass``, attached by the
runtime) also update a glass map with the mapper's own steps (glass hits kept occupied, registration,
Bayesian update). The registration sigma of such a scan comes from its pose's uncertainty *relative to the
map it registers on*: the front end's filter covariance (``KeyScan.cov``, relative to the map built so
far), not the uncertainty relative to the map frame's anchor, which a corrected map no longer carries.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from glassmap.grid import MapGrid, OccupancyGrid, OccupancyParams
from glassmap.mapping import BeamGlass, GlassMapper, MapperConfig
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.motion import compose, compose_jacobians


def relative_sigma(key: KeyScan, ranges: np.ndarray, range_sigma: float = 0.01,
                   range_sigma_per_m: float = 0.001) -> np.ndarray:
    """Per-beam registration sigma (m) of a key scan from its covariance relative to the map:
    sqrt(sigma_xy^2 + (r sigma_theta)^2 + sigma_r(r)^2) as ``PoseEstimator.registration_sigma``, with the
    laser pose's covariance from ``key.cov`` (the mount's lever arm included). NaN for non-finite ranges."""
    ja, _ = compose_jacobians(key.pose, key.mount)
    cov = ja @ key.cov @ ja.T
    sxy2 = max(float(np.linalg.eigvalsh(cov[:2, :2]).max()), 0.0)
    sth2 = max(float(cov[2, 2]), 0.0)
    r_in = np.asarray(ranges, dtype=np.float64)
    r = np.where(np.isfinite(r_in), r_in, 0.0)
    sr = range_sigma + range_sigma_per_m * r
    return np.where(np.isfinite(r_in), np.sqrt(sxy2 + r * r * sth2 + sr * sr), np.nan)


SIGMA_SOURCES = ("map", "anchor")
"""Where an online registration sigma comes from: "map", the current pose's covariance relative to the map
built so far (``PoseEstimator.scan_relative_covariance``, the filter's, as ``KeyScan.cov``); "anchor", the
reported covariance (relative to the map frame's anchor: the filter's plus the matched map region's)."""


def online_sigma(estimator, estimate, ranges: np.ndarray, source: str = "map") -> np.ndarray:
    """Per-beam registration sigma (m) of the scan the ``estimator`` (a ``PoseEstimator``) has just placed at
    ``estimate``, from the covariance ``source`` (:data:`SIGMA_SOURCES`); the formula is
    ``PoseEstimator.registration_sigma``'s."""
    if source == "map":
        estimate = replace(estimate, covariance=estimator.scan_relative_covariance())
    elif source != "anchor":
        raise ValueError(f"registration sigma source must be one of {SIGMA_SOURCES}, got {source!r}")
    return estimator.registration_sigma(estimate, ranges)


class NoClassifier:
    """The classifier of a glass map rebuilt from key scans: p(glass) comes with the key scans, so nothing
    may classify (and no network is loaded)."""

    uses_echoes = False

    def predict_scan(self, *args, **kwargs) -> np.ndarray:
        raise RuntimeError("a glass map rebuilt from key scans takes p(glass) from the key scans (KeyScan.p_glass); "
                           "it does not classify")


class MapRebuild:
    """The occupancy grid of ``keys`` at ``poses`` (N, 3) (base, map frame), and with ``mapper`` a
    :class:`GlassMapper` whose glass map is built from the key scans that carry p(glass), built a few key
    scans at a time (:meth:`step`) so that a worker can do other work in between. ``grid``: an empty grid to
    build on (default: a new one of ``resolution``), e.g. one aligned with a blueprint. The key scans and poses
    are taken as they are now (a later key scan is not included)."""

    def __init__(self, keys: Sequence[KeyScan], poses: np.ndarray, occupancy: OccupancyParams = OccupancyParams(),
                 resolution: float = 0.05, mapper: MapperConfig | None = None, grid: MapGrid | None = None) -> None:
        self.occ = OccupancyGrid(grid if grid is not None else MapGrid(resolution), occupancy)
        self.glass = GlassMapper(self.occ, mapper, classifier=NoClassifier()) if mapper is not None else None
        self._poses = np.asarray(poses, dtype=np.float64)
        self._keys = list(keys)[: len(self._poses)]
        self._next = 0

    @property
    def done(self) -> bool:
        return self._next >= len(self._keys)

    def step(self, n: int) -> bool:
        """Integrate the next ``n`` key scans; returns :attr:`done`."""
        gm = self.glass
        for pose, k in zip(self._poses[self._next:self._next + n], self._keys[self._next:self._next + n]):
            lp = compose(pose, k.mount)
            if gm is None or k.scan is None or k.p_glass is None:
                self.occ.integrate(lp, k.angles, k.ranges, k.range_max)
                continue
            scan = k.scan
            gm.integrate(scan, lp)
            use = np.isfinite(k.p_glass)
            inc = np.full(k.p_glass.shape, np.nan) if k.incidence is None else k.incidence
            beams = BeamGlass(np.asarray(k.p_glass, dtype=np.float64), np.asarray(inc, dtype=np.float64))
            if gm.config.glass_hits_occupy or gm.config.protect == "hits":
                gm.mark_glass_hits(beams, use, scan, lp)
            gm.register(beams, use, scan, lp, relative_sigma(k, scan.ranges))
        self._next = min(self._next + n, len(self._keys))
        return self.done


def rebuild_maps(keys: Sequence[KeyScan], poses: np.ndarray, occupancy: OccupancyParams = OccupancyParams(),
                 resolution: float = 0.05, mapper: MapperConfig | None = None, grid: MapGrid | None = None
                 ) -> tuple[OccupancyGrid, GlassMapper | None]:
    """The maps of :class:`MapRebuild`, built at once."""
    job = MapRebuild(keys, poses, occupancy, resolution, mapper, grid)
    while not job.step(100):
        pass
    return job.occ, job.glass
