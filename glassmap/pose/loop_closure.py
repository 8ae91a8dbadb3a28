"""Loop-closure detection and verification: the current key scan against older submaps.

Every ``check_every``-th key scan is matched (the front end's correlative matcher, a wide window) against
the closed submaps that the robot left at least ``min_travel`` m of path ago and whose centres lie within
``search_radius`` of the current pose in the pose graph's solution, composed at the graph's poses in the
frame of the nearest one. The prior is the graph's
relative pose; the window is ``window_sigmas`` times an assumed drift of ``drift_xy + drift_xy_per_m * d``
(m) and ``drift_yaw + drift_yaw_per_m * d`` (rad) over the d metres travelled since the submap, clipped to
the matcher's maximum.

A match becomes a *candidate* when it is good on its own: at least ``min_overlap`` of its end points fall on
cells the old submaps observed, and of those at least ``min_inliers`` lie on their walls (:func:`agreement`);
the peak not on the window's border; at least ``min_directions`` directions of pose space constrained by
at least ``constrained_points`` end points each (a corridor's long axis is not: there a closure constrains
the sideways position and the heading only); its covariance in those directions no wider than
``max_sigma_xy`` / ``max_sigma_yaw``. Along the directions it does not constrain, the closure's edge
carries a standard deviation of ``free_sigma`` (m; rad for a pure heading direction) and the graph's own
relative pose (the match's prior) as its value: it corrects only what the scan observed. Glass and long
corridors make wrong but good-looking matches likely, and a wrong closure is worse than none, so a
candidate is *accepted* only when a second candidate from a different key scan (at least
``pair_min_travel`` m away, at most ``pair_max_travel``) agrees with it: the relative pose between the two
scans implied by the two matches (through the graph between the two submaps' anchors, if they differ)
equals the front end's (locally exact) relative pose within ``pair_xy`` / ``pair_yaw`` in the directions
both matches constrain. After a pair is accepted, each new candidate must agree in the same way with the
last accepted closure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from glassmap.grid import OccupancyGrid
from glassmap.pose.field import LikelihoodField
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.matcher import CorrelativeMatcher, MatcherConfig, MatchResult, constrained_directions, select_points
from glassmap.pose.motion import compose, compose_jacobians, points_to_map, relative
from glassmap.pose.submaps import Submap, SubmapStore
from glassmap.types import wrap_angle


@dataclass(frozen=True)
class LoopClosureConfig:
    """Candidate search, verification and edge settings (lengths m, angles rad); see the module docstring.
    cov_floor: (x, y, yaw) standard deviations added to a closure's match covariance (the submap's own
    error). min_directions: 3 closes only where the scan constrains the whole pose; 2 also in corridors."""

    check_every: int = 4
    min_travel: float = 20.0
    search_radius: float = 5.0
    window_sigmas: float = 3.0
    drift_xy: float = 0.05
    drift_xy_per_m: float = 0.005
    drift_yaw: float = float(np.radians(0.5))
    drift_yaw_per_m: float = float(np.radians(0.02))
    min_overlap: float = 0.3
    min_inliers: float = 0.7
    constrained_points: float = 10.0
    min_directions: int = 2
    free_sigma: float = 1.0
    max_sigma_xy: float = 0.03
    max_sigma_yaw: float = float(np.radians(0.5))
    pair_min_travel: float = 0.3
    pair_max_travel: float = 5.0
    pair_xy: float = 0.03
    pair_yaw: float = float(np.radians(0.5))
    cov_floor: tuple[float, float, float] = (0.01, 0.01, float(np.radians(0.2)))
    matcher: MatcherConfig = field(default_factory=lambda: MatcherConfig(
        xy_window_max=1.0, yaw_window_max=float(np.radians(8.0)), max_points=300, min_quality=0.0))

    def __post_init__(self) -> None:
        if self.min_directions not in (1, 2, 3):
            raise ValueError(f"min_directions must be 1, 2 or 3 (constrained directions of x, y, yaw), "
                             f"got {self.min_directions}")


@dataclass(frozen=True)
class Candidate:
    """A verified-on-its-own match of key scan ``node`` (path length ``travel`` m, front-end pose
    ``frontend``) against ``submap``: ``pose`` (3,) the node in the submap's anchor frame, ``cov`` (3, 3);
    ``proj`` (3, 3) projects pose space (that frame) onto the directions the match constrains."""

    node: int
    travel: float
    frontend: np.ndarray
    submap: int
    anchor: int
    pose: np.ndarray
    cov: np.ndarray
    inliers: float
    proj: np.ndarray = field(default_factory=lambda: np.eye(3))


@dataclass
class LoopStats:
    """Counters: checks (matches tried), candidates (passed the single-match tests), accepted, rejected_pair
    (candidates no other candidate agreed with), and per reason of single-match rejection."""

    checks: int = 0
    candidates: int = 0
    accepted: int = 0
    rejected_pair: int = 0
    rejected: dict = field(default_factory=dict)

    def reject(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1


def agreement(fld: LikelihoodField, occ: OccupancyGrid, pts: np.ndarray, pose: np.ndarray, p_floor: float
              ) -> tuple[float, float]:
    """(overlap, inlier share) of base-frame end points ``pts`` at ``pose`` against an old map: overlap is
    the share of points falling on cells the map has observed (free or occupied); the inlier share is,
    among those, the share within 2 sigma_hit of a wall.
    Points on unobserved cells say nothing (the old submaps saw less than the current scan does); a point
    on observed free space contradicts the match."""
    xy = points_to_map(pose, pts)
    cells = occ.grid.world_to_cell(xy)
    ok = occ.grid.in_bounds(cells)
    known = np.zeros(len(pts), dtype=bool)
    known[ok] = ~occ.unknown()[cells[ok, 1], cells[ok, 0]]
    if not known.any():
        return 0.0, 0.0
    inl = fld.log_likelihood(xy[known]) > np.log(np.exp(-2.0) + p_floor)
    return float(known.mean()), float(inl.mean())


def _projector(h: np.ndarray) -> np.ndarray:
    """(3, 3) projection of pose space onto the directions ``h`` (rows, from :func:`constrained_directions`)
    along the others (the identity when all three are constrained)."""
    if h.shape[0] == 3:
        return np.eye(3)
    return h.T @ np.linalg.solve(h @ h.T, h)


class LoopCloser:
    """Finds and verifies loop closures; :meth:`check` returns the closures to add to the graph."""

    def __init__(self, config: LoopClosureConfig = LoopClosureConfig(), sigma_hit: float = 0.03) -> None:
        self.config = config
        self.matcher = CorrelativeMatcher(config.matcher)
        self.sigma_hit = sigma_hit
        self.stats = LoopStats()
        self._pending: list[Candidate] = []
        self._last_accepted: Candidate | None = None

    def select_submaps(self, store: SubmapStore, poses: np.ndarray, node: int, travel: float) -> list[Submap]:
        """The eligible submaps (closed, left >= min_travel m of path ago) whose centres lie within
        search_radius of node's pose in ``poses`` (the graph's solution, (N, 3)), nearest first."""
        cfg = self.config
        found = []
        here = poses[node, :2]
        for sm in store.submaps:
            if not sm.closed or travel - sm.end < cfg.min_travel:
                continue
            a = poses[sm.anchor]
            c, s = np.cos(a[2]), np.sin(a[2])
            centre = a[:2] + np.array([[c, -s], [s, c]]) @ sm.centre()
            d = float(np.hypot(*(centre - here)))
            if d < cfg.search_radius:
                found.append((d, sm.index, sm))
        return [sm for _, _, sm in sorted(found, key=lambda t: (t[0], t[1]))]

    def match(self, store: SubmapStore, group: list[Submap], poses: np.ndarray, key: KeyScan, prior: np.ndarray,
              travel: float) -> tuple[MatchResult | None, float, float]:
        """Match ``key`` against the submaps ``group`` (placed by ``poses``, in the first one's anchor frame)
        around ``prior`` (its pose in that frame); returns (match, overlap, inlier share) (see
        :func:`agreement`)."""
        cfg = self.config
        d = max(travel - max(sm.end for sm in group), 0.0)
        sxy = cfg.drift_xy + cfg.drift_xy_per_m * d
        syaw = cfg.drift_yaw + cfg.drift_yaw_per_m * d
        a0 = poses[group[0].anchor]
        anchors = np.array([relative(a0, poses[sm.anchor]) for sm in group])
        pts, w, _ = select_points(key.angles, key.ranges, key.mount, cfg.matcher)
        fld, occ = store.field(group, anchors)
        res = self.matcher.match(fld, pts, w, prior, np.diag([sxy ** 2, sxy ** 2, syaw ** 2]))
        if res is None:
            return None, 0.0, 0.0
        overlap, inliers = agreement(fld, occ, pts, res.pose, fld.params.p_floor)
        return res, overlap, inliers

    def single_check(self, res: MatchResult | None, overlap: float, inliers: float) -> tuple[str, np.ndarray]:
        """('', the projector onto the directions the match constrains, see :func:`_projector`) if ``res``
        passes the single-match tests, else (the reason it fails, that projector or the identity)."""
        cfg = self.config
        if res is None:
            return "no match", np.eye(3)
        if res.edge:
            return "peak on the window border", np.eye(3)
        if overlap < cfg.min_overlap:
            return "small overlap", np.eye(3)
        if inliers < cfg.min_inliers:
            return "few inliers", np.eye(3)
        h = constrained_directions(res.information, res.lever, self.sigma_hit, cfg.constrained_points)
        if h.shape[0] < cfg.min_directions:
            return "unconstrained direction", np.eye(3)
        proj = _projector(h)
        cov = proj @ res.covariance @ proj.T
        ev = np.linalg.eigvalsh(cov[:2, :2])
        if np.sqrt(max(ev.max(), 0.0)) > cfg.max_sigma_xy or np.sqrt(max(cov[2, 2], 0.0)) > cfg.max_sigma_yaw:
            return "wide covariance", proj
        return "", proj

    def edge_covariance(self, res: MatchResult, proj: np.ndarray) -> np.ndarray:
        """Covariance (3, 3; x, y, yaw in the submap's anchor frame) of a closure's edge: the match's in the
        directions it constrains (``proj``, see :func:`_projector`) plus ``cov_floor``, and ``free_sigma``
        along the others."""
        cfg = self.config
        free = np.eye(3) - proj
        cov = proj @ res.covariance @ proj.T + cfg.free_sigma ** 2 * free @ free.T + np.diag(np.square(cfg.cov_floor))
        return 0.5 * (cov + cov.T)

    def agree(self, a: Candidate, b: Candidate, poses: np.ndarray) -> bool:
        """Whether two candidates imply the same relative pose between their scans as the front end does, in
        the directions both matches constrain: b's match against where a's match and the front end's
        relative pose put it."""
        cfg = self.config
        pb, proj_b = b.pose, b.proj
        if a.submap != b.submap:  # bring b into a's submap frame through the graph
            link = relative(poses[a.anchor], poses[b.anchor])
            _, turn = compose_jacobians(link, pb)
            pb = compose(link, pb)
            proj_b = turn @ proj_b @ turn.T
        d = pb - compose(a.pose, relative(a.frontend, b.frontend))
        d[2] = float(wrap_angle(d[2]))
        d = proj_b @ (a.proj @ d)
        return float(np.hypot(d[0], d[1])) <= cfg.pair_xy and abs(float(d[2])) <= cfg.pair_yaw

    def check(self, store: SubmapStore, poses: np.ndarray, node: int, key: KeyScan, travel: float
              ) -> list[Candidate]:
        """Try key scan ``key`` (graph node ``node``, ``travel`` m of path so far; ``poses`` the graph's
        solution) for a loop closure; returns the candidates accepted now (0, 1 or 2)."""
        cfg = self.config
        group = self.select_submaps(store, poses, node, travel)
        if not group:
            return []
        sm = group[0]
        self.stats.checks += 1
        prior = relative(poses[sm.anchor], poses[node])
        res, overlap, inliers = self.match(store, group, poses, key, prior, travel)
        why, proj = self.single_check(res, overlap, inliers)
        if why:
            self.stats.reject(why)
            return []
        self.stats.candidates += 1
        # the match's pose only in the directions it observes; along the others the prior (the graph's own
        # relative pose), so that the closure does not pull along what the scan did not see
        step = np.asarray(res.pose, dtype=np.float64) - prior
        step[2] = float(wrap_angle(step[2]))
        pose = prior + proj @ step
        pose[2] = float(wrap_angle(pose[2]))
        cand = Candidate(node, travel, np.asarray(key.pose, dtype=np.float64), sm.index, sm.anchor, pose,
                         self.edge_covariance(res, proj), inliers, proj)
        last = self._last_accepted
        if last is not None and cand.travel - last.travel <= cfg.pair_max_travel:
            if self.agree(last, cand, poses):
                self._last_accepted = cand
                self.stats.accepted += 1
                return [cand]
            self.stats.rejected_pair += 1
            return []
        # a first closure needs a partner among the recent pending candidates
        kept = [p for p in self._pending if cand.travel - p.travel <= cfg.pair_max_travel]
        self.stats.rejected_pair += len(self._pending) - len(kept)  # no partner came in time
        self._pending = kept
        for p in reversed(self._pending):
            if cand.travel - p.travel >= cfg.pair_min_travel and self.agree(p, cand, poses):
                self._pending = []
                self._last_accepted = cand
                self.stats.accepted += 2
                return [p, cand]
        self._pending.append(cand)
        return []
