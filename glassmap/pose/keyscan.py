"""What the pose estimator hands the pose graph for each key scan (see ``PoseEstimator.last_key_scan``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from glassmap.types import Scan


@dataclass(frozen=True)
class KeyScan:
    """One key scan as the front end placed it.

    seq / stamp (s, host time): the scan's; pose (3,): corrected base pose (x, y m, yaw rad) in the front
    end's map frame; cov (3, 3): the filter's covariance relative to the map built so far (m^2, rad^2);
    odom (3,): the wheel-odometry pose (odom frame) at ``stamp``; fused_dims: directions of the scan match
    fused into the pose (0: placed by odometry alone); written: the scan was integrated into the map;
    angles (n,) rad, ranges (n,) m: the scan as matched (laser frame, after any de-skew); range_max (m);
    mount (3,): laser pose in the base frame. scan / p_glass / incidence: the raw scan, its p(glass) per beam
    (NaN: not classified) and incidence angle per beam (rad, NaN: none), attached by the runtime's glass path
    so the glass map can be rebuilt at corrected poses (None: occupancy only). jump (3,): on the key scan whose
    match ended a lost track, the correction that match applied (map frame; m, m, rad: the relocalisation),
    None on every other. anchors (m,) int: for a key scan whose match was fused, for each matched point that
    landed on a cell earlier key scans placed end points in, the mean of their indices in the front end's chain
    (:class:`~glassmap.pose.chain.DriftChain`), rounded; None otherwise. constrained (k, 3), k = 1 or 2: for a
    match fused in fewer than three directions, the directions of pose space (x, y, yaw; map frame) it
    constrained (:func:`~glassmap.pose.matcher.constrained_directions`); None otherwise."""

    seq: int
    stamp: float
    pose: np.ndarray
    cov: np.ndarray
    odom: np.ndarray
    fused_dims: int
    written: bool
    angles: np.ndarray
    ranges: np.ndarray
    range_max: float
    mount: np.ndarray
    scan: Scan | None = None
    p_glass: np.ndarray | None = None
    incidence: np.ndarray | None = None
    jump: np.ndarray | None = None
    anchors: np.ndarray | None = None
    constrained: np.ndarray | None = None
