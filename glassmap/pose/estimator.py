"""The online pose estimator: odometry prediction + correlative scan matching, fused by an EKF.

Per scan (``update``): predict the base pose in the map frame with the motion-noise model from the wheel
odometry up to the newest message at or before the scan (the filter's state lives there), and carry the
motion extrapolated past it to the scan's stamp apart (``scan_pose``; the next message replaces it, so a
match does not correct it into the state, and its error widens the prediction). On key scans only (motion filter: moved >= 5 cm or turned >= 2 deg
since the last key scan, or 20 scans since it; ``EstimatorConfig.keyframe_*``): match the scan against a
likelihood field of the occupancy grid built so far, fuse the match (pose + covariance from the score
distribution) with the prediction, then integrate the scan into the shared occupancy grid at the
corrected laser pose. The map frame is anchored at
``EstimatorConfig.initial_pose``; there is no loop closure (drift is bounded by matching against the map
built so far, not removed).

Glass: a beam that hits glass near normal incidence returns from the pane, a beam at a larger angle
passes through and returns from what is behind, so the same pane is sometimes in the scan and sometimes
not, and the map holds it only partly. The likelihood-field score is robust to that (a floor per point),
and ``glass_weighting`` down-weights beams whose end point falls on a cell the ``"glass"`` layer of the
grid believes is glass (see :meth:`PoseEstimator.glass_weights`); ``protect_glass`` stops beams through
glass from clearing such cells. ``glassmap pose eval --glass-weighting`` measures the effect.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field as dc_field, replace

import numpy as np

from glassmap.grid import OccupancyGrid, OccupancyParams, MapGrid
from glassmap.pose.chain import ChainConfig, DriftChain
from glassmap.pose.estimator_jit import add_hits, mean_keys, registration_sigmas, seen_through_glass
from glassmap.pose.field import FieldParams, LikelihoodField
from glassmap.pose.filter import PoseEKF, offset_consensus
from glassmap.pose.filter_jit import carried, rotated
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.matcher import (CorrelativeMatcher, MatcherConfig, MatchResult, constrained_directions,
                                   select_points, slid_to_prior)
from glassmap.pose.motion import (MotionNoise, OdometryBuffer, compose, compose_jacobians, deskew, points_to_map,
                                  relative)
from glassmap.types import Odometry, PoseEstimate, Scan, wrap_angle

log = logging.getLogger(__name__)

GLASS_LAYER = "glass"
# chi-square 99.99 % points for 1..15 degrees of freedom (a streak of lost_after = 5 matches has at most 15)
_CHI2_9999_BY_DOF = (15.14, 18.42, 21.11, 23.51, 25.74, 27.86, 29.88, 31.83, 33.72, 35.56, 37.37, 39.13, 40.87,
                     42.58, 44.26)
# the gate's points by directions fused, relative to 3 dof (EstimatorConfig.gate_chi2)
_CHI2_9999_SHARE = {k: _CHI2_9999_BY_DOF[k - 1] / _CHI2_9999_BY_DOF[2] for k in (1, 2, 3)}


def _chi2_9999(dof: int) -> float:
    """The chi-square 99.99 % point for ``dof`` >= 1 degrees of freedom: the table, beyond it the
    Wilson-Hilferty approximation (within 1 % there). No scipy here: its first import stalls the scan path
    for about a second."""
    if dof <= len(_CHI2_9999_BY_DOF):
        return _CHI2_9999_BY_DOF[dof - 1]
    z = 3.7190164854556804  # the standard normal's 99.99 % point
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * np.sqrt(2.0 / (9.0 * dof))) ** 3


def _offsets_second_moment(offsets, dirs, prior: np.ndarray) -> np.ndarray:
    """Mean of y y^T over pose offsets (3,) of which only the directions ``dirs[k]`` (rows) are measured: the
    unmeasured part of each is its expectation given the measured part under the covariance ``prior``
    (P H^T (H P H^T)^-1 H y)."""
    m = np.zeros((3, 3))
    for y, h in zip(offsets, dirs):
        v = prior @ h.T @ np.linalg.solve(h @ prior @ h.T, h @ y)
        m += np.outer(v, v)
    return m / len(offsets)


def _psd(m: np.ndarray) -> np.ndarray:
    """The symmetric part of ``m`` with negative eigenvalues set to 0."""
    vals, vecs = np.linalg.eigh(0.5 * (m + m.T))
    return (vecs * np.maximum(vals, 0.0)) @ vecs.T


HIT_LAYERS = ("pose_hit_sx", "pose_hit_sy", "pose_hit_n")
KEY_LAYER = "pose_hit_key"  # per cell: the sum over its end points (``pose_hit_n``) of their key scans' chain indices
_NO_LAYER = np.zeros((0, 0), np.float32)  # (add_hits without KEY_LAYER)
MAP_UNCERTAINTY = ("chain", "off")  # EstimatorConfig.map_uncertainty


@dataclass(frozen=True)
class EstimatorConfig:
    """Settings of :class:`PoseEstimator`. Lengths in metres, angles in radians, times in seconds.

    laser_mount: laser pose (x, y, yaw) in the base frame (the simulated and the real Pioneer carry the
        Hokuyo 0.1 m ahead of the axle). initial_pose / initial_sigma: the map frame is anchored here. The
        map frame is defined by the first pose, so its uncertainty is zero: 0.1 mm, 0.1 mrad (not 0, to
        keep the filter's covariance positive definite). The map inherits it: an initial yaw variance is a
        rotation of the whole map about the start. Set it larger when the start pose is only known in another
        frame.
    range_sigma, range_sigma_per_m: range noise of the laser, sigma_r = range_sigma + range_sigma_per_m * r
        (Hokuyo UTM-30LX: 10 mm + 1 mm/m, as in the simulator's laser model).
    keyframe_distance, keyframe_angle, keyframe_max_scans: motion filter. Every scan gets the EKF prediction
        (pose + covariance at its stamp), but scan matching, the likelihood-field rebuild and the occupancy
        bookkeeping/integration run only on key scans: the first scan, and any scan whose predicted pose has
        moved >= keyframe_distance (m, default 0.05) or turned >= keyframe_angle (rad, default 2 deg) since
        the last key scan, or that comes keyframe_max_scans (default 20, 0 = never forced) scans after it.
        keyframe_distance = keyframe_angle = 0 makes every scan a key scan.
    field_incremental: bring the likelihood field up to date with the grid at every key scan, before its
        match, computing only the cells whose nearest wall or wall point changed
        (:meth:`LikelihoodField.refresh`: the field a rebuild of the same crop gives); it is rebuilt around
        the robot once the robot is ``field_recentre`` (m, in x or y) from the crop's centre (on the next
        non-key scan, as the periodic rebuild below), and on a key scan when the robot nears the crop's
        edge or the grid grew. Off by default: what it gains and loses is in docs/pose.md, "Session 37".
    field_refresh_scans: without ``field_incremental``, the likelihood field is rebuilt from the grid after
        this many key scans were integrated, on the next scan (a non-key scan, so the cost does not add to
        a key scan's), and on a key scan when the robot nears the edge of the field's crop or the grid grew.
    background_field: compute that periodic rebuild in a worker thread (the crop's occupied cells are taken
        on the non-key scan, its end-point layers read in place, which only key scans write; the result is
        installed at the next key scan, waiting for it if needed), so its 10-20 ms stay off the
        scan-processing path; the results are the same as without it.
    gate_chi2: matches whose innovation has a squared Mahalanobis distance above this are rejected
        (chi-square 99.99 % points by the number of directions fused: 15.1, 18.4, 21.1 for 1, 2, 3; this is
        the 3-dof one, the others scale with it). A rejected match is neither fused nor integrated into the
        map: the scan is placed only where the prediction and the map agree.
    constrained_points: a direction of pose space is fused only if the match's end points carry the
        information of at least this many points squarely facing it (see
        :func:`~glassmap.pose.matcher.constrained_directions`); the others (along a featureless corridor)
        are not measured by the scan, and the covariance keeps growing along them.
    slide_to_prior: a match that leaves translations unconstrained measures the pose at the prior's place
        along them (:func:`~glassmap.pose.matcher.slid_to_prior`): a peak at an alias along a corridor is
        not read as a heading error.
    lost_after: this many consecutive key scans whose match was rejected by the gate are judged together.
        If they agree with each other (one common offset from the prediction) and, for an offset that shifts
        the pose by ``alias_min_shift`` (m) or more (an alias of a repetitive corridor is a door frame or so
        away), the last scan fits at its match better than anywhere near the prediction (by
        ``relocalise_lead``, mean end-point log-likelihood), the prediction is wrong: the track is ``lost``
        (status of :class:`~glassmap.types.PoseEstimate`; logged as an error), the covariance is widened by
        that offset and the map is not updated until a match passes the gate again (the search window grows with the
        covariance, up to the matcher's maximum). Otherwise the matches are ambiguous (aliases of a
        repetitive corridor, which disagree with each other or fit no better than the prediction): the track
        stays ``degraded`` (logged as a warning), the estimate follows odometry with its growing covariance,
        and the rejected scans stay out of the map.
    glass_weighting: glass-aware matching from the ``"glass"`` layer of the grid (log-odds): behind_glass_weight
        multiplies the weight of beams that pass a believed-glass cell more than glass_behind_margin (m)
        before their end (through-glass returns and mirror ghosts; 1 turns it off); glass_min_weight is the
        weight of a beam ending on a cell of p(glass) = 1 (linear from 1 at p = 0.5; 1, the default, leaves
        beams ending on glass as they are). See glass_weights.
    protect_glass: cells with p(glass) above glass_protect_p are not cleared by beams passing through.
    integrate: integrate each key scan into the occupancy grid at the corrected pose.
    subcell_walls: keep the mean end-point position per cell (layers ``pose_hit_*``) and measure the
        likelihood field's distances to it rather than to cell centres (see LikelihoodField.rebuild).
    deskew: undo the base's motion during the laser's sweep on key scans (beam k is taken at stamp + k *
        time_increment; the UTM-30LX sweeps its 270 deg in about 19 ms, so a turn at 60 deg/s bends a scan
        by 1.1 deg and 0.5 m/s stretches it by 9 mm) with the buffered odometry before matching and
        integrating. Off by default because the simulator takes every beam of a scan from the pose at its
        stamp (there is nothing to undo there, and ``glassmap pose eval`` cannot measure the benefit); turn
        it on with a real laser whose ``Scan.stamp`` is the time of the first beam.
    map_uncertainty: what the reported covariance (:meth:`PoseEstimator.covariance`) is relative to.
        "chain" (default): the map frame's anchor, through the chain of key scans from the start
        (:class:`~glassmap.pose.chain.DriftChain`, ``chain``; the pose graph's marginal without closures); it
        only grows, also where the route comes back onto older map (a loop), which only a pose graph's closure
        corrects. "off": the map built so far only (the filter's covariance). The gate, the search window, the
        fusion and ``KeyScan.cov`` always use the filter's covariance relative to the map built so far.
    chain: the drift model of "chain" (:class:`~glassmap.pose.chain.ChainConfig`).
    correlated_matches: report the filter's covariance allowing for the error that consecutive matches
        share (``PoseEKF.actual_cov``, correlation = share of the previous match's wall blocks this one uses);
        off (default), the filter's own covariance (which fuses every match as independent) is reported
        (docs/pose.md says why).
    """

    laser_mount: tuple[float, float, float] = (0.1, 0.0, 0.0)
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    initial_sigma: tuple[float, float, float] = (1e-4, 1e-4, 1e-4)
    motion: MotionNoise = dc_field(default_factory=MotionNoise)
    matcher: MatcherConfig = dc_field(default_factory=MatcherConfig)
    likelihood: FieldParams = dc_field(default_factory=FieldParams)
    occupancy: OccupancyParams = dc_field(default_factory=OccupancyParams)
    range_sigma: float = 0.01
    range_sigma_per_m: float = 0.001
    keyframe_distance: float = 0.05
    keyframe_angle: float = float(np.radians(2.0))
    keyframe_max_scans: int = 20
    field_incremental: bool = False
    field_recentre: float = 1.0
    field_refresh_scans: int = 10
    background_field: bool = True
    gate_chi2: float = 21.1
    constrained_points: float = 10.0
    slide_to_prior: bool = True
    lost_after: int = 5
    relocalise_lead: float = 0.5
    alias_min_shift: float = 0.1
    glass_weighting: bool = False
    glass_min_weight: float = 1.0
    behind_glass_weight: float = 0.2
    glass_behind_margin: float = 0.15
    protect_glass: bool = False
    glass_protect_p: float = 0.7
    integrate: bool = True
    deskew: bool = False
    map_uncertainty: str = "chain"
    chain: ChainConfig = dc_field(default_factory=ChainConfig)
    correlated_matches: bool = False
    subcell_walls: bool = True

    def __post_init__(self) -> None:
        if self.keyframe_distance < 0 or self.keyframe_angle < 0 or self.keyframe_max_scans < 0:
            raise ValueError("keyframe_distance (m), keyframe_angle (rad) and keyframe_max_scans must be >= 0, got "
                             f"{self.keyframe_distance}, {self.keyframe_angle}, {self.keyframe_max_scans}")
        if self.field_refresh_scans < 1:
            raise ValueError(f"field_refresh_scans must be >= 1, got {self.field_refresh_scans}")
        if not self.field_recentre > 0:
            raise ValueError(f"field_recentre (m) must be > 0, got {self.field_recentre}")
        if self.map_uncertainty not in MAP_UNCERTAINTY:
            raise ValueError(f"map_uncertainty must be one of {MAP_UNCERTAINTY}, got {self.map_uncertainty!r}")


@dataclass
class EstimatorStats:
    """Counters and timings (s) of the last scan and totals."""

    scans: int = 0
    keyframes: int = 0  # scans that were matched against the map and integrated (motion filter passed)
    last_keyframe: bool = False  # whether the last scan was a key scan
    matched: int = 0
    no_match: int = 0
    gated: int = 0
    wide_searches: int = 0  # key-scan matches searched over the widest heading window (after a rejected match)
    field_rebuilds: int = 0
    field_updates: int = 0
    t_core: float = 0.0  # prediction + matching + covariance + fusion of the last scan
    t_field: float = 0.0  # likelihood-field rebuild or update during the last scan (0 if none)
    t_integrate: float = 0.0  # occupancy integration of the last scan
    last_match: MatchResult | None = None
    unconstrained: int = 0  # key-scan matches with at least one direction not fused (degenerate geometry)
    status: str = "ok"  # track status: "ok", "degraded" (last key scan's match rejected), "lost"
    status_reason: str = ""
    gated_streak: int = 0  # consecutive key scans whose match the gate rejected
    lost_events: int = 0  # times the track became lost
    ambiguous_events: int = 0  # streaks of gated matches judged aliases (not relocalised on)
    last_fused_dims: int = 0  # directions fused on the last key scan (0: none)


class PoseEstimator:
    """Online pose + covariance of the base in the map frame, one estimate per scan.

    ``predict(odom)`` buffers wheel odometry (any rate); ``update(scan)`` returns the :class:`PoseEstimate`
    at ``scan.stamp`` and integrates the scan into ``occupancy`` (shared with the glass mapper).

    Covariance. The EKF tracks the pose relative to the map built so far (odometry noise and match
    covariances; with ``correlated_matches``, ``ekf.actual_cov`` also counts the error consecutive matches
    share, see :mod:`glassmap.pose.filter`): that is what gates and fuses the matches. Reported alone it would
    be overconfident, because the map itself is only as good as the poses that built it, so by default
    (``map_uncertainty = "chain"``) the reported covariance is the drift of the chain of key scans from the
    start (:class:`~glassmap.pose.chain.DriftChain`).
    """

    def __init__(self, config: EstimatorConfig = EstimatorConfig(), occupancy: OccupancyGrid | None = None) -> None:
        self.config = config
        self.occupancy = occupancy if occupancy is not None else OccupancyGrid(MapGrid(), config.occupancy)
        self.mount = np.asarray(config.laser_mount, dtype=np.float64)
        if self.mount.shape != (3,) or not np.all(np.isfinite(self.mount)):
            raise ValueError(f"laser_mount must be 3 finite numbers (x, y, yaw), got {config.laser_mount!r}")
        self.ekf = PoseEKF(np.asarray(config.initial_pose, dtype=np.float64),
                           np.diag(np.square(np.asarray(config.initial_sigma, dtype=np.float64))))
        self.chain = DriftChain(config.chain, self.ekf.cov)  # the key scans' drift (map_uncertainty "chain")
        self.odometry = OdometryBuffer()
        self.field = LikelihoodField(config.likelihood)
        self.matcher = CorrelativeMatcher(config.matcher)
        self.stats = EstimatorStats()
        # the streak of gated matches: (offset from the prediction, covariance, directions, filter covariance)
        self._gated: deque[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=config.lost_after)
        # while matches are rejected by the gate (until a streak is judged lost) and while a streak is judged
        # ambiguous: the second moment (map frame; m, rad) of its matches' offsets from the prediction, added to
        # the reported covariance only (it does not open the gate)
        self._gated_spread: np.ndarray | None = None
        self._jump: np.ndarray | None = None  # the correction of the match that ended a lost track (relocalised)
        self._constrained = np.eye(3)  # the directions the last fused match constrained (rows, pose space)
        self._last_odom: np.ndarray | None = None
        self._last_stamp: float | None = None
        self._since_rebuild = 0
        self._key_pose: np.ndarray | None = None  # EKF pose (map frame) at the last key scan
        self._since_key = 0
        self._executor: ThreadPoolExecutor | None = None
        self._pending_field: Future | None = None  # a field rebuild running in the worker thread
        self._matched_keys: np.ndarray | None = None  # wall blocks (map-frame keys) under the last match
        # the filter's state is the base at the newest odometry time at or before the scan (``_last_t``); the
        # motion extrapolated past it to the scan (base frame) is carried apart, with (s extrapolated, v m/s,
        # omega rad/s, s held beyond the limit), because the next odometry message replaces it
        self._ext = np.zeros(3)
        # after a key scan's match at an extrapolated stamp: the scan's own posterior (pose, covariance of the
        # filter part), which also corrects the extrapolated motion; None: compose(filter pose, _ext)
        self._scan_post: tuple[np.ndarray, np.ndarray] | None = None
        self._extrapolated = (0.0, 0.0, 0.0, 0.0)
        # scan_relative_covariance of the last scan, with the objects it was computed from (see there)
        self._relative_cov: tuple[tuple, np.ndarray] | None = None
        self._last_t: float | None = None
        if config.subcell_walls:
            for name in HIT_LAYERS:
                if name not in self.occupancy.grid.layer_names:
                    self.occupancy.grid.add_layer(name, 0.0, np.float32)
            if config.chain.revisit_gap > 0 and KEY_LAYER not in self.occupancy.grid.layer_names:
                self.occupancy.grid.add_layer(KEY_LAYER, 0.0, np.float32)  # the chain's revisits (anchors)
        # optional callable -> (H, W) bool mask of cells the occupancy update must not clear (e.g. the glass
        # mapper's ``protect_mask``); called after the grid has grown to contain the scan
        self.protect_mask_fn = None
        self.last_key_scan: KeyScan | None = None  # the last key scan as placed (for a pose graph)

    # ------------------------------------------------------------------ inputs
    def predict(self, odom: Odometry) -> None:
        """Buffer one wheel-odometry message (odom frame, host time); the prediction itself happens in
        :meth:`update` at the scan's time."""
        self.odometry.add(odom)

    def is_keyframe_due(self) -> bool:
        """Whether the scan being updated (after prediction) passes the motion filter (see EstimatorConfig)."""
        cfg = self.config
        if self._key_pose is None:
            return True
        if cfg.keyframe_max_scans > 0 and self._since_key >= cfg.keyframe_max_scans:
            return True
        d = relative(self._key_pose, self.scan_pose())
        return bool(np.hypot(d[0], d[1]) >= cfg.keyframe_distance or abs(d[2]) >= cfg.keyframe_angle)

    def update(self, scan: Scan) -> PoseEstimate:
        """Estimate the base pose at ``scan.stamp``; on a key scan (motion filter, see EstimatorConfig) also
        fuse the scan match and integrate the scan (``stats.last_keyframe`` tells which); never raises
        on bad scan contents (no beams, all max range, NaN): it then falls back to odometry, whose
        covariance keeps growing. A non-finite stamp is a ValueError."""
        cfg = self.config
        st = self.stats
        t0 = time.perf_counter()
        stamp = float(scan.stamp)
        if not np.isfinite(stamp):
            raise ValueError(f"scan {scan.seq} has a non-finite stamp {scan.stamp!r}; stamps are host seconds")
        # ---- prediction from odometry interpolated to the scan time. The filter predicts only up to the
        # newest odometry message (measured motion); the rest, extrapolated with that message's velocity, is
        # carried apart (``_ext``): the next message replaces it, so a match must not correct it into the state
        t_state = stamp
        self._scan_post = None
        if len(self.odometry):
            t_state = min(stamp, float(self.odometry.newest))
            odom_state = self.odometry.pose_at(t_state)
            self._ext = relative(odom_state, self.odometry.pose_at(stamp))
            self._extrapolated = self.odometry.extrapolation(stamp)
            delta = relative(self._last_odom, odom_state) if self._last_odom is not None else np.zeros(3)
            self._last_odom = odom_state
        else:
            delta = np.zeros(3)
        dt = 0.0 if self._last_t is None else max(t_state - self._last_t, 0.0)
        self._last_t = t_state if self._last_t is None else max(self._last_t, t_state)
        self._last_stamp = stamp
        self.ekf.predict(delta, cfg.motion.covariance(delta, dt))
        t_pred = time.perf_counter() - t0
        self._since_key += 1
        key = self.is_keyframe_due()
        st.last_keyframe = key
        st.t_field = 0.0
        if not key:
            if self._pending_field is None and self._field_due():
                # a periodic refresh or a re-centring that is due runs here, between key scans, not on the next
                # key scan
                self._rebuild_field(background=cfg.background_field)
            st.t_core, st.t_integrate, st.last_match = t_pred, 0.0, None
            st.scans += 1
            return self.estimate(stamp)
        self._since_key = 0
        st.keyframes += 1

        # ---- likelihood field (rebuilt every few key scans or when needed; timed separately)
        self._install_pending_field()
        # (a field with no walls yet is rebuilt as soon as a scan has been integrated: otherwise the first
        # field_refresh_scans key scans would all be placed by odometry alone, and the map keeps their errors)
        if ((not cfg.field_incremental and self._since_rebuild >= cfg.field_refresh_scans)
                or (not self.field.ready and self._since_rebuild > 0)
                or self.field.needs_rebuild(self.occupancy, self.scan_pose()[:2], cfg.matcher.range_max * 0.25 + 1.0)):
            self._rebuild_field()
        elif cfg.field_incremental and self.field.arrays is not None:
            self._update_field()

        # ---- matching + fusion
        t2 = time.perf_counter()
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        angles = scan.angles
        if cfg.deskew and len(self.odometry) and ranges.size > 1:
            angles, ranges = self.deskewed(scan)
        res = None
        if ranges.size and self.field.ready:
            pts, w, idx = select_points(angles, ranges, self.mount, cfg.matcher)
            if cfg.glass_weighting and GLASS_LAYER in self.occupancy.grid.layer_names and idx.size:
                w = w * self.glass_weights(self.laser_pose_of(self.scan_pose()), angles[idx], ranges[idx])
            prior_cov = self._carried(self.ekf.cov) + self.extrapolation_covariance()
            if st.status == "degraded":
                # the last match disagreed with the prediction, whose heading may be off by more than its
                # covariance says (laser and odometry stamps out of step while turning): search the widest
                # heading window, so that the match is the scan's best fit and not a local one near a wrong
                # heading; the translation window stays the prediction's, since a wide one reaches the
                # aliases of a repetitive corridor (the gate still judges against the filter's covariance)
                st.wide_searches += 1
                mc = cfg.matcher
                prior_cov = prior_cov + np.diag([0.0, 0.0, (mc.yaw_window_max / mc.window_sigmas) ** 2])
            res = self.matcher.match(self.field, pts, w, self.scan_pose(), prior_cov)
            if res is not None and cfg.slide_to_prior:
                res = replace(res, pose=slid_to_prior(res.pose, self.scan_pose(), prior_cov, res.information,
                                                      res.lever, cfg.likelihood.sigma_hit, cfg.constrained_points,
                                                      cfg.alias_min_shift))
        st.last_match = res
        accepted = self._fuse(res, pts if res is not None else None, w if res is not None else None, scan.seq)
        anchors = self._anchors(pts) if accepted and st.last_fused_dims > 0 else None
        st.t_core = t_pred + (time.perf_counter() - t2)

        # ---- map update at the corrected pose
        t3 = time.perf_counter()
        # a scan whose match the gate rejected is not written into the map (nor while the track is lost):
        # it disagrees with the map where the prediction says the robot is, so one of them is wrong
        write = st.status != "lost" and (accepted or res is None)
        if cfg.integrate and ranges.size and write:
            protect = None  # a callable: evaluated after integrate() has grown the grid to hold the scan
            if self.protect_mask_fn is not None:
                protect = self.protect_mask_fn
            elif cfg.protect_glass:
                protect = self.glass_protect_mask
            self.occupancy.integrate(self.laser_pose_of(self.scan_pose()), angles, ranges,
                                     scan.geometry.range_max, protect=protect)
        if ranges.size and write and cfg.subcell_walls:
            # bookkeeping of the end points at the corrected pose, also when another component (the glass
            # mapper, ``integrate=False``) updates the occupancy grid with this scan at the same pose
            end = self._end_points(angles, ranges, scan.geometry.range_max)
            if not cfg.integrate and not self._grid_holds_scan(end, ranges):
                self.occupancy.ensure_scan_extent(self.laser_pose_of(self.scan_pose()), angles, ranges,
                                                  scan.geometry.range_max)
            self._store_hits(angles, ranges, scan.geometry.range_max, end=end)
        st.t_integrate = time.perf_counter() - t3
        self._key_pose = self.scan_pose()
        self.last_key_scan = KeyScan(
            seq=scan.seq, stamp=stamp, pose=self._key_pose.copy(), cov=self.scan_relative_covariance().copy(),
            odom=np.zeros(3) if self._last_odom is None else compose(self._last_odom, self._ext),
            fused_dims=st.last_fused_dims, written=bool(write), angles=np.asarray(angles), ranges=ranges,
            range_max=float(scan.geometry.range_max), mount=self.mount, jump=self._jump, anchors=anchors,
            constrained=self._constrained if 0 < st.last_fused_dims < 3 else None)
        self._jump = None
        self.chain.add(self.last_key_scan)
        self._since_rebuild += 1
        st.scans += 1
        return self.estimate(stamp)

    def _fuse(self, res: MatchResult | None, pts: np.ndarray | None, w: np.ndarray | None, seq: int) -> bool:
        """Gate and fuse a key scan's match (the directions it constrains), update the track status;
        False when the match was rejected by the gate or there was none (True also when it constrained no
        direction: nothing to fuse, nothing contradicted)."""
        cfg, st = self.config, self.stats
        st.last_fused_dims = 0
        if res is None:
            st.no_match += 1
            return False
        h = constrained_directions(res.information, res.lever, cfg.likelihood.sigma_hit, cfg.constrained_points)
        if h.shape[0] < 3:
            st.unconstrained += 1
        if h.shape[0] == 0:
            return True
        hm = None if h.shape[0] == 3 else h
        z, r = self._measurement_at_state(res)
        _, _, d2 = self.ekf.innovation(z, r, hm)
        gate = cfg.gate_chi2 * _CHI2_9999_SHARE[h.shape[0]]
        if d2 > gate:
            st.gated += 1
            st.gated_streak += 1
            y = z - self.ekf.pose
            y[2] = float(wrap_angle(y[2]))
            self._gated.append((y, r, np.eye(3) if hm is None else hm, self.ekf.cov.copy()))
            if st.gated_streak >= cfg.lost_after:
                if st.status != "lost":
                    self._judge_gated_streak(seq, d2, gate, res, pts, w)
            else:
                # until the streak is judged: reported as uncertain by the offsets of its matches, in case the
                # prediction is what is wrong (stamps out of step while turning)
                ys, _, hs, _ = zip(*self._gated)
                self._gated_spread = _offsets_second_moment(ys, hs, self.ekf.cov)
                if st.status == "ok":
                    st.status_reason = f"scan match rejected by the gate (squared distance {d2:.0f} > {gate:.1f})"
                    log.info("scan %d: %s", seq, st.status_reason)
                    st.status = "degraded"
            return False
        rho = self._match_overlap(pts, res.pose) if cfg.correlated_matches else 0.0
        if np.any(self._ext):
            # the scan's own posterior: its prior (the filter's pose carried along the extrapolated motion) and
            # the match, fused in the same directions; that is where the scan is mapped and reported
            # (the filter's covariance, as the gain uses; with correlated_matches the scan's reported covariance
            # is then this one, not the consider covariance, until the next scan)
            scan = PoseEKF(self.scan_pose(), self._carried(self.ekf.cov) + self.extrapolation_covariance())
            scan.correct(res.pose, res.covariance, 0.0, hm)
        before = self.ekf.pose.copy()
        self.ekf.correct(z, r, rho, hm)
        if np.any(self._ext):
            self._scan_post = (scan.pose.copy(), scan.cov.copy())
        st.matched += 1
        st.last_fused_dims = h.shape[0]
        self._constrained = h
        if st.status == "lost":
            self._jump = self.ekf.pose - before
            self._jump[2] = float(wrap_angle(self._jump[2]))
            log.warning("pose track recovered at scan %d: a match agrees with the prediction again (relocalised "
                        "by %.2f m, %.1f deg)", seq, float(np.hypot(*self._jump[:2])), np.degrees(self._jump[2]))
        st.status, st.status_reason, st.gated_streak = "ok", "", 0
        self._gated.clear()
        self._gated_spread = None
        return True

    def _lead_over_prediction(self, res: MatchResult, pts: np.ndarray, w: np.ndarray) -> float:
        """How much better (mean end-point log-likelihood per unit weight) the scan fits at the match's peak than
        at the best pose near the prediction (a 5 x 5 x 5 lattice over +-3 standard deviations of the filter's
        covariance, at least +-1 cell and +-0.2 deg)."""
        prior = self.scan_pose()
        sd = np.sqrt(np.diag(self._carried(self.ekf.cov)))
        half = 3.0 * np.maximum(sd, [self.field.resolution, self.field.resolution, np.radians(0.2)])
        axes = [np.linspace(-h, h, 5) for h in half]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) + prior
        poses = np.vstack([res.peak_pose[None], grid])
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        x = poses[:, 0:1] + c * pts[None, :, 0] - s * pts[None, :, 1]
        y = poses[:, 1:2] + s * pts[None, :, 0] + c * pts[None, :, 1]
        ll = self.field.log_likelihood(np.stack([x.ravel(), y.ravel()], axis=1)).reshape(len(poses), -1)
        score = ll @ w / w.sum()
        return float(score[0] - score[1:].max())

    def _judge_gated_streak(self, seq: int, d2: float, gate: float, res: MatchResult, pts: np.ndarray,
                            w: np.ndarray) -> None:
        """After ``lost_after`` consecutive matches rejected by the gate: if they agree with each other (one
        common offset from the prediction, :func:`~glassmap.pose.filter.offset_consensus`) and, for a shift of
        ``alias_min_shift`` or more, the scan prefers the match to anywhere near the prediction
        (:meth:`_lead_over_prediction`), the prediction is what is wrong: the track is lost and the covariance
        (with it the search window) is widened by that offset, so the next such match relocalises. Otherwise
        (aliases of a repetitive corridor) the matches are what is ambiguous: the estimate keeps following
        odometry with its growing covariance, the status stays ``degraded`` and the scans stay out of the map;
        the reported covariance (:meth:`off_chain_covariance`, not the filter's) is widened by the second
        moment of the matches' offsets, in case one of them is right, until a match is fused again."""
        st, cfg = self.stats, self.config
        ys, rs, hs, ps = zip(*self._gated)
        p_now = self.ekf.cov
        # the prediction drifted by odometry alone since each match (nothing was fused in the streak)
        covs = [r + _psd(p_now - p) for r, p in zip(rs, ps)]
        offset, chi2, dof = offset_consensus(list(ys), covs, list(hs))
        why = ""
        if dof > 0 and chi2 > _chi2_9999(dof):
            why = f"disagree with the prediction and with each other (chi-square {chi2:.0f}, {dof} dof)"
        elif np.hypot(offset[0], offset[1]) >= cfg.alias_min_shift:
            lead = self._lead_over_prediction(res, pts, w)
            if lead < cfg.relocalise_lead:
                why = (f"agree on an offset of {100 * np.hypot(offset[0], offset[1]):.0f} cm, "
                       f"{np.degrees(offset[2]):.1f} deg, but the scan fits near the prediction about as well "
                       f"(by {lead:.2f} per point)")
        if why:
            if not st.status_reason.startswith("ambiguous"):
                st.ambiguous_events += 1
                st.status_reason = (f"ambiguous scan matches: {st.gated_streak} in a row {why}; the estimate "
                                    f"follows odometry")
                log.warning("scan %d: %s", seq, st.status_reason)
            st.status = "degraded"
            self._gated_spread = _offsets_second_moment(ys, hs, p_now)
            return
        self._gated_spread = None
        self.ekf.cov = self.ekf.cov + np.outer(offset, offset)
        self.ekf.actual_cov = self.ekf.actual_cov + np.outer(offset, offset)
        st.lost_events += 1
        st.status_reason = (f"{st.gated_streak} consecutive scan matches disagree with the prediction beyond their "
                            f"covariance, by a common offset of ({offset[0]:.2f} m, {offset[1]:.2f} m, "
                            f"{np.degrees(offset[2]):.1f} deg) (last: squared distance {d2:.0f} > {gate:.1f})")
        log.error("pose track lost at scan %d: %s", seq, st.status_reason)
        st.status = "lost"

    def deskewed(self, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """(angles, ranges) of ``scan`` as seen from the laser at ``scan.stamp`` (the first beam), undoing the
        base's motion during the sweep with the buffered odometry (beam k is taken at stamp + k *
        geometry.time_increment); see :func:`glassmap.pose.motion.deskew`."""
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        n = ranges.size
        sweep = scan.geometry.time_increment * (n - 1)
        if n < 2 or sweep <= 0 or not len(self.odometry):
            return scan.angles, ranges
        t0 = float(scan.stamp)
        delta = relative(self.odometry.pose_at(t0), self.odometry.pose_at(t0 + sweep))
        return deskew(scan.angles, ranges, self.mount, delta, np.arange(n) / (n - 1))

    def _rebuild_field(self, background: bool = False) -> None:
        """Rebuild the likelihood field around the current pose (time in ``stats.t_field``); with
        ``background`` the computation runs in a worker thread and is installed at the next key scan."""
        t = time.perf_counter()
        g = self.occupancy.grid
        pts_layers = tuple(g[n] for n in HIT_LAYERS) if self.config.subcell_walls else None
        # the end-point layers are read in place, by the worker too: only a key scan writes them (_store_hits),
        # after _install_pending_field has waited for the result
        inputs = self.field.snapshot(self.occupancy, self.scan_pose()[:2], pts_layers, copy=False)
        if background:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="likelihood-field")
            self._pending_field = self._executor.submit(self.field.compute, inputs)
        else:
            self.field.install(self.field.compute(inputs))
        self._since_rebuild = 0
        self.stats.field_rebuilds += 1
        self.stats.t_field = time.perf_counter() - t

    def _field_due(self) -> bool:
        """Whether a rebuild of the likelihood field is due between key scans: periodic, or with
        ``field_incremental`` once the robot is ``field_recentre`` from the crop's centre."""
        cfg = self.config
        if not cfg.field_incremental:
            return self._since_rebuild >= cfg.field_refresh_scans
        return self.field.ready and bool(np.max(np.abs(self.scan_pose()[:2] - self.field.center)) > cfg.field_recentre)

    def _update_field(self) -> None:
        """Bring the likelihood field up to date with the grid on its crop (time in ``stats.t_field``)."""
        t = time.perf_counter()
        g = self.occupancy.grid
        self.field.refresh(self.occupancy, tuple(g[n] for n in HIT_LAYERS) if self.config.subcell_walls else None)
        self._since_rebuild = 0
        self.stats.field_updates += 1
        self.stats.t_field += time.perf_counter() - t

    def _install_pending_field(self) -> None:
        """Install a field computed in the background (waits for it: results do not depend on timing)."""
        if self._pending_field is not None:
            t = time.perf_counter()
            self.field.install(self._pending_field.result())
            self._pending_field = None
            self.stats.t_field += time.perf_counter() - t

    def __getstate__(self) -> dict:  # the worker thread does not travel (process pools, copies)
        self._install_pending_field()
        state = dict(self.__dict__)
        state["_executor"] = None
        return state

    def _match_overlap(self, pts: np.ndarray, pose: np.ndarray) -> float:
        """Share (0..1) of the wall blocks under this match's end points (base-frame pts at pose) that the
        previous match's end points fell in too: the correlation of the two matches' errors (they share
        the error of the map where they overlap). A block is the (2 pool + 1)^2 cells whose end points the
        likelihood field averages into one wall point (``FieldParams.pool``), so two matches using the same
        wall estimate count as overlapping; blocks are keyed by map-frame position, so a grown grid does not
        change them."""
        block = (2 * self.field.params.pool + 1) * self.occupancy.grid.resolution
        keys = np.floor(points_to_map(pose, pts) / block)
        keys = np.unique(keys.astype(np.int64) @ np.array([1, 1 << 32], dtype=np.int64))
        prev, self._matched_keys = self._matched_keys, keys
        if prev is None or keys.size == 0:
            return 0.0
        return float(np.isin(keys, prev).mean())

    def _end_points(self, angles: np.ndarray, ranges: np.ndarray, range_max: float) -> np.ndarray:
        """Map-frame end points (n, 2) (m) of the beams with a hit (finite, <= range_max) at the scan's laser
        pose."""
        hit = np.isfinite(ranges) & (ranges <= range_max)
        lp = self.laser_pose_of(self.scan_pose())
        r = ranges[hit]
        a = lp[2] + angles[hit]
        return lp[:2] + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    def _grid_holds_scan(self, end: np.ndarray, ranges: np.ndarray) -> bool:
        """Whether the occupancy grid already holds all that ``OccupancyGrid.ensure_scan_extent`` would grow
        it to for this scan (so that call can be skipped): the box of the scan's end points ``end`` (n, 2)
        (:meth:`_end_points`, the same values as the grid's) and the laser position, plus its 1 m margin.
        The space a hit clears lies between the laser and the end point, inside that box; beams without a
        return that clear space (``no_return_range`` > 0) are not in ``end``, so then False (ask the grid)."""
        if self.occupancy.params.no_return_range > 0 and np.isposinf(ranges).any():
            return False
        lp = self.laser_pose_of(self.scan_pose())
        g = self.occupancy.grid
        if len(end):
            ex, ey = end[:, 0], end[:, 1]  # 1-D reductions (an axis-0 one of (n, 2) costs several times more)
            lo = np.array([min(ex.min(), lp[0]), min(ey.min(), lp[1])])
            hi = np.array([max(ex.max(), lp[0]), max(ey.max(), lp[1])])
        else:
            lo = hi = lp[:2]
        c_lo, c_hi = g.world_to_cell(lo - 1.0), g.world_to_cell(hi + 1.0)
        return bool(c_lo.min() >= 0 and c_hi[0] <= g.shape[1] - 1 and c_hi[1] <= g.shape[0] - 1)

    def _store_hits(self, angles: np.ndarray, ranges: np.ndarray, range_max: float,
                    end: np.ndarray | None = None) -> None:
        """Accumulate this scan's end points per cell (offset from the cell corner, m) for sub-cell walls, and
        this key scan's chain index per end point (``KEY_LAYER``); ``end``: the end points (:meth:`_end_points`)
        if already computed."""
        if end is None:
            end = self._end_points(angles, ranges, range_max)
        if not len(end):
            return
        g = self.occupancy.grid
        sx, sy, n = (g[name] for name in HIT_LAYERS)
        key = g[KEY_LAYER] if KEY_LAYER in g.layer_names else _NO_LAYER
        add_hits(sx, sy, n, key, np.float32(len(self.chain)), end, float(g.origin[0]), float(g.origin[1]),
                 float(g.resolution))

    def _anchors(self, pts: np.ndarray) -> np.ndarray | None:
        """``KeyScan.anchors`` of the matched points ``pts`` (n, 2, base frame) at the scan's pose: the mean chain
        index of the end points in each one's cell (cells inside the grid that hold end points)."""
        g = self.occupancy.grid
        if KEY_LAYER not in g.layer_names:
            return None
        return mean_keys(g[KEY_LAYER], g[HIT_LAYERS[2]], points_to_map(self.scan_pose(), pts), float(g.origin[0]),
                         float(g.origin[1]), float(g.resolution))

    # ------------------------------------------------------------------ outputs
    def scan_pose(self) -> np.ndarray:
        """Base pose (3,) in the map frame at the last scan's stamp: the filter's pose (at the newest odometry
        message) with the motion extrapolated past it."""
        if self._scan_post is not None:
            return self._scan_post[0].copy()
        return compose(self.ekf.pose, self._ext)

    def extrapolation_covariance(self) -> np.ndarray:
        """3x3 covariance (map frame) of the motion extrapolated past the newest odometry message to the last
        scan (:meth:`MotionNoise.extrapolation_covariance`; zero when the scan is inside the odometry)."""
        dt, v, w, held = self._extrapolated
        if dt <= 0 and held <= 0:
            return np.zeros((3, 3))
        return rotated(self.ekf.pose, self.config.motion.extrapolation_covariance(v, dt, w, held))

    def _carried(self, cov: np.ndarray) -> np.ndarray:
        """A 3x3 covariance ``cov`` of the filter's pose carried along the extrapolated motion to the scan."""
        return carried(self.ekf.pose, self._ext, np.asarray(cov, dtype=np.float64))

    def _measurement_at_state(self, res: MatchResult) -> tuple[np.ndarray, np.ndarray]:
        """The match (base pose at the scan's stamp, covariance) as a measurement of the filter's pose (at the
        newest odometry message): the extrapolated motion is undone and its error added to the measurement's
        covariance (the next odometry message replaces it, so it is not the state's error)."""
        if not np.any(self._ext):
            return res.pose, res.covariance
        back = relative(self._ext, np.zeros(3))  # the inverse motion
        ja, _ = compose_jacobians(res.pose, back)
        return compose(res.pose, back), ja @ res.covariance @ ja.T + self.extrapolation_covariance()

    def covariance(self) -> np.ndarray:
        """Reported 3x3 covariance (map frame) at the last scan (``EstimatorConfig.map_uncertainty``). "chain":
        the key scans' drift from the start carried to the scan plus :meth:`off_chain_covariance`. "off": the
        filter's, relative to the map built so far (:meth:`scan_relative_covariance`)."""
        if self.config.map_uncertainty == "chain":
            stamp = 0.0 if self._last_stamp is None else self._last_stamp
            return self.chain.covariance_at(self.scan_pose(), stamp) + self.off_chain_covariance()
        return self.scan_relative_covariance()

    def off_chain_covariance(self) -> np.ndarray:
        """3x3 covariance (map frame) of what the chain of key scans does not hold: the pose held past the
        extrapolation limit while the base may still move (odometry late; the motion extrapolated up to the
        limit is covered by the chain's odometry noise since the key scan) and, while the track is lost, the
        filter's covariance (widened by the matches' disagreement; the key scans came from the poses it lost)
        or, while scan matches are rejected by the gate (the track degraded, or its streak judged ambiguous), the
        second moment of their offsets from the prediction: in case they are right and the prediction is not."""
        _, v, w, held = self._extrapolated
        cov = np.zeros((3, 3))
        if held > 0:
            cov = rotated(self.ekf.pose, self.config.motion.extrapolation_covariance(v, 0.0, w, held))
        if self.stats.status == "lost":
            cov = cov + self.scan_relative_covariance()
        elif self._gated_spread is not None:
            cov = cov + self._gated_spread
        return cov

    def scan_relative_covariance(self) -> np.ndarray:
        """3x3 covariance of the pose at the last scan relative to the map built so far (the filter's, carried
        along the extrapolated motion, or the scan's own posterior after a match at an extrapolated stamp)."""
        if self._scan_post is not None:
            return self._scan_post[1]
        # asked several times per scan (estimate, registration sigma, map bookkeeping, key scan): computed
        # once per state. The filter and update() replace these arrays rather than write into them, so the
        # same objects mean the same state
        inputs = (self.ekf.pose, self.ekf.actual_cov, self._ext, self._extrapolated)
        cached = self._relative_cov
        if cached is None or any(a is not b for a, b in zip(cached[0], inputs)):
            cached = self._relative_cov = (inputs, self._carried(self.ekf.actual_cov) + self.extrapolation_covariance())
        return cached[1].copy()

    def estimate(self, stamp: float | None = None) -> PoseEstimate:
        """The current estimate (base, map frame, at the last scan) with the reported covariance."""
        x, y, yaw = self.scan_pose()
        s = self._last_stamp if stamp is None else stamp
        return PoseEstimate(stamp=0.0 if s is None else s, x=float(x), y=float(y), yaw=float(yaw),
                            covariance=self.covariance(), status=self.stats.status)

    def laser_pose_of(self, base_pose: np.ndarray) -> np.ndarray:
        """Laser pose (3,) in the map frame for a base pose (3,) in the map frame."""
        return compose(np.asarray(base_pose, dtype=np.float64), self.mount)

    def laser_pose(self, estimate: PoseEstimate) -> np.ndarray:
        """Laser pose (3,) (x, y, yaw) in the map frame of an estimate of the base."""
        return self.laser_pose_of(estimate.pose)

    def laser_covariance(self, estimate: PoseEstimate) -> np.ndarray:
        """3x3 covariance of the laser pose (the mount's lever arm turns yaw uncertainty into position)."""
        return carried(np.asarray(estimate.pose, dtype=np.float64), self.mount,
                       np.asarray(estimate.covariance, dtype=np.float64))

    def registration_sigma(self, estimate: PoseEstimate, ranges: np.ndarray) -> np.ndarray:
        """Per-beam registration sigma (m) of the beam end points, shape (n,):

            sigma(r)^2 = sigma_xy^2 + (r * sigma_theta)^2 + sigma_r(r)^2

        sigma_xy: sqrt of the larger eigenvalue of the laser position covariance (the worst direction, so a
        corridor's long axis counts); sigma_theta: yaw standard deviation; sigma_r(r) = range_sigma +
        range_sigma_per_m * r (laser range noise). A yaw error moves an end point sideways by r * dtheta, a
        position error moves it rigidly; the three are treated as independent. NaN / inf ranges -> NaN.
        """
        r_in = np.asarray(ranges, dtype=np.float64)
        cov = self.laser_covariance(estimate)
        sxy2 = max(float(np.linalg.eigvalsh(cov[:2, :2]).max()), 0.0)
        sth2 = max(float(cov[2, 2]), 0.0)
        return registration_sigmas(r_in.reshape(-1), sxy2, sth2, float(self.config.range_sigma),
                                   float(self.config.range_sigma_per_m)).reshape(r_in.shape)

    # ------------------------------------------------------------------ glass
    def glass_probability_at(self, xy: np.ndarray) -> np.ndarray:
        """p(glass) (n,) of the grid cells under map-frame points xy (n, 2); 0.5 off the grid or without a
        ``"glass"`` layer."""
        g = self.occupancy.grid
        xy = np.asarray(xy, dtype=np.float64)
        out = np.full(xy.shape[0], 0.5)
        if GLASS_LAYER not in g.layer_names or xy.size == 0:
            return out
        ok = np.all(np.isfinite(xy), axis=1)
        cells = g.world_to_cell(np.where(ok[:, None], xy, 0.0))
        ok &= g.in_bounds(cells)
        lo = g[GLASS_LAYER][cells[ok, 1], cells[ok, 0]].astype(np.float64)
        out[ok] = 1.0 / (1.0 + np.exp(-lo))
        return out

    def glass_weights(self, laser_pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """Matching weight per beam (n,) from the ``"glass"`` layer: falling linearly from 1 to
        ``glass_min_weight`` as p(glass) of the end point's cell goes from 0.5 to 1 (a pane is seen only near
        normal incidence, so the map holds it only partly), times ``behind_glass_weight`` for a beam whose
        path crosses a cell believed glass (p > 0.5) more than ``glass_behind_margin`` (m) before its end:
        what is seen through a pane, and mirror images (ghost points) of what is in front of it, which lie
        behind the pane at the unfolded path length."""
        r = np.where(np.isfinite(ranges), ranges, 0.0)
        a = laser_pose[2] + angles
        u = np.stack([np.cos(a), np.sin(a)], axis=1)
        w = np.ones(r.size)
        if self.config.glass_min_weight < 1.0:  # (at 1, the default, the end points' p(glass) changes nothing)
            p = self.glass_probability_at(laser_pose[:2] + r[:, None] * u)
            w = 1.0 - (1.0 - self.config.glass_min_weight) * np.clip(2.0 * p - 1.0, 0.0, 1.0)
        if self.config.behind_glass_weight < 1.0 and r.size:
            g = self.occupancy.grid
            reach = np.maximum(r - self.config.glass_behind_margin, 0.0)
            steps = np.arange(0.0, float(reach.max()) + g.resolution, 0.5 * g.resolution)  # half-cell steps
            behind = seen_through_glass(g[GLASS_LAYER], float(g.origin[0]), float(g.origin[1]), float(g.resolution),
                                        float(laser_pose[0]), float(laser_pose[1]), np.ascontiguousarray(u[:, 0]),
                                        np.ascontiguousarray(u[:, 1]), reach, steps)
            w = np.where(behind, w * self.config.behind_glass_weight, w)
        return w

    def glass_protect_mask(self) -> np.ndarray | None:
        """(H, W) bool: cells whose p(glass) exceeds ``glass_protect_p`` (None without a glass layer)."""
        g = self.occupancy.grid
        if GLASS_LAYER not in g.layer_names:
            return None
        lo_t = np.log(self.config.glass_protect_p / (1.0 - self.config.glass_protect_p))
        return g[GLASS_LAYER] > lo_t
