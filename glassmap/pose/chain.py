"""The chain of key scans: how the front end's error in the map frame grows from one key scan to the next.

Each key scan is placed relative to the one before it (the front end's relative pose between them, a
*sequential edge*). The covariance of that step is the wheel-odometry noise of the motion and, when both key
scans were placed by a scan match, the information sum with ``match_scale`` times the two poses' filter
covariances carried through the relative pose (:func:`relative_covariance`: those are relative to the map built
so far, which keeps consecutive key scans consistent, and large along directions a scan did not constrain).
Over many steps the front end drifts far less than a random walk of these steps (every match is anchored to the
same map), so their standard deviations are scaled by ``chain_scale``, except along the heading next to a key
scan matched in fewer than three directions (a corridor: there the step along it is odometry's).

Compounded along the key scans this is the covariance of the front end's pose relative to where it started:
what the front end reports (:class:`DriftChain`, ``EstimatorConfig.map_uncertainty = "chain"``) and, without
loop closures, the pose graph's marginal (``GraphBackEnd``, whose sequential edges are these steps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from glassmap.pose.keyscan import KeyScan
from glassmap.pose.motion import MotionNoise, compose_covariance, relative


def relative_covariance(a: np.ndarray, b: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of ``relative(a, b)``'s (x, y, yaw) for poses a, b (3,) with independent errors of
    covariances cov_a, cov_b (map frame, additive x, y, yaw)."""
    c, s = np.cos(a[2]), np.sin(a[2])
    d = np.asarray(b[:2], dtype=np.float64) - np.asarray(a[:2], dtype=np.float64)
    rt = np.array([[c, s], [-s, c]])
    ja = np.zeros((3, 3))
    ja[:2, :2] = -rt
    ja[:2, 2] = np.array([[-s, c], [-c, -s]]) @ d
    ja[2, 2] = -1.0
    jb = np.zeros((3, 3))
    jb[:2, :2] = rt
    jb[2, 2] = 1.0
    out = ja @ cov_a @ ja.T + jb @ cov_b @ jb.T
    return 0.5 * (out + out.T)


@dataclass(frozen=True)
class ChainConfig:
    """motion: the odometry noise model of a step; match_scale: multiplies the matched poses' covariance of a
    step both ends of which were matched; min_sigma: (x, y, yaw) standard deviations added to every step (m, m,
    rad); chain_scale: multiplies a step's (x, y, yaw) standard deviations (x, y in the frame of its first key
    scan); x keeps its scale 1 where a key scan at either end was matched in fewer than three directions;
    scale_sigma: standard deviation of the map's scale error (relative), reported by :class:`DriftChain` only:
    the matches' forward bias, carried from key scan to key scan through the map, places a pose off by about
    scale times its displacement from the start (docs/pose.md, "Start-up bias" and "Session 30").
    revisit_gap (m; 0: off) and revisit_share, used by :class:`DriftChain` only: a key scan whose match was fused
    with at least ``revisit_share`` of its matched points on cells whose end points came (on average) from a key
    scan it reached along a path longer than their straight-line distance plus ``revisit_gap`` (map placed before
    the route turned or came back) is placed against those cells in the directions its match constrained, not
    only by the step from the key scan before it."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    match_scale: float = 0.1
    min_sigma: tuple[float, float, float] = (0.001, 0.001, 0.0005)
    chain_scale: tuple[float, float, float] = (0.55, 0.22, 0.17)
    scale_sigma: float = 0.0016
    revisit_gap: float = 0.01
    revisit_share: float = 0.5

    @cached_property
    def floor(self) -> np.ndarray:
        """diag(min_sigma^2) (3, 3): the covariance added to every step (read only)."""
        out = np.diag(np.square(self.min_sigma))
        out.flags.writeable = False
        return out

    def step_covariance(self, prev: KeyScan, key: KeyScan) -> np.ndarray:
        """Covariance (3, 3) of the step from key scan ``prev`` to ``key`` (in ``prev``'s frame), before
        ``chain_scale``."""
        rel = relative(prev.pose, key.pose)
        floor = self.floor
        cov = self.motion.covariance(rel, max(key.stamp - prev.stamp, 0.0)) + floor
        if key.fused_dims and prev.fused_dims:  # both placed by matches: fuse with their relative pose
            m = self.match_scale * relative_covariance(prev.pose, key.pose, prev.cov, key.cov) + floor
            cov = np.linalg.inv(np.linalg.inv(cov) + np.linalg.inv(m))
        return cov

    @staticmethod
    def jump_covariance(prev: KeyScan, key: KeyScan) -> np.ndarray:
        """Covariance (3, 3, in ``prev``'s frame) a step gains where ``key`` ended a lost track: the outer product
        of its jump's translation (``KeyScan.jump``); zero on every other step. Not scaled by ``chain_scale``.
        The heading is left out: every later match measures it against the map's walls, and a wrong heading
        would be rejected again, while a translation to an alias (a door frame further along a corridor) is
        consistent with the map there and never contradicted."""
        if key.jump is None:
            return np.zeros((3, 3))
        return relative_covariance(prev.pose, key.pose, np.zeros((3, 3)), jump_translation(key))

    def scaled(self, cov: np.ndarray, partial: bool) -> np.ndarray:
        """A step's covariance ``cov`` with ``chain_scale`` applied; ``partial``: a key scan at either end was
        matched in fewer than three directions (x keeps its noise)."""
        s = np.array(self.chain_scale)
        if partial:
            s[0] = 1.0
        s = np.diag(s)
        return s @ cov @ s

    def carried(self, node: np.ndarray, cov: np.ndarray, rel: np.ndarray, dt: float) -> np.ndarray:
        """Covariance (3, 3, map frame) of ``compose(node, rel)``: a key scan's pose ``node`` of covariance
        ``cov`` carried along the front end's motion ``rel`` since it (over ``dt`` s), plus that motion's own
        odometry noise and ``min_sigma`` (an unscaled step to a pose that is not a key scan)."""
        q = self.motion.covariance(rel, max(dt, 0.0)) + self.floor
        return compose_covariance(node, rel, cov, q)


_UNBOUNDED = 1e6  # variance (m^2, rad^2) along the directions a partial match left free: the chain's is kept there


def jump_translation(key: KeyScan) -> np.ndarray:
    """Outer product (3, 3, map frame) of the translation of ``key``'s relocalisation jump (zero heading)."""
    shift = np.array([key.jump[0], key.jump[1], 0.0])
    return np.outer(shift, shift)


def partial_step(prev: KeyScan, key: KeyScan) -> bool:
    """Whether a key scan at either end of a step was matched in fewer than three directions."""
    return min(key.fused_dims, prev.fused_dims) < 3


def psd_min(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance (3, 3) that is in every direction the smaller of ``a`` (positive definite) and ``b``
    (positive semi-definite): both diagonalised together, the smaller variance kept along each common axis."""
    lo = np.linalg.cholesky(a)
    inv = np.linalg.inv(lo)
    lam, u = np.linalg.eigh(inv @ b @ inv.T)
    m = lo @ u
    out = (m * np.minimum(lam, 1.0)) @ m.T
    return 0.5 * (out + out.T)


class DriftChain:
    """The covariance (map frame, x, y, yaw) of the front end's pose compounded along its key scans from the
    start: a sequential step per key scan (:meth:`ChainConfig.step_covariance`, scaled), and from the newest key
    scan to the current pose the motion since it (:meth:`ChainConfig.carried`).

    Where the route comes back onto older map, a key scan's match places it against cells that earlier key
    scans placed (``KeyScan.anchors``: per matched point, the mean index in this chain of the key scans whose end
    points are in its cell); its error is then theirs carried to its pose plus its own error relative to the map
    (``KeyScan.cov``). Of that and the step from the key scan
    before it, the smaller is kept in each direction (:func:`psd_min`; ``ChainConfig.revisit_gap``); a match
    fused in fewer than three directions (``KeyScan.constrained``: along a corridor) bounds only those, the
    steps' covariance stays along the others. The
    averaged anchors' covariance bounds the error of a match on several of them from above. What relocalisations
    added (``KeyScan.jump``) is kept: a jump to an alias is consistent with the older map there."""

    def __init__(self, config: ChainConfig, initial_cov: np.ndarray) -> None:
        self.config = config
        self.key: KeyScan | None = None  # the newest key scan
        self.cov = np.asarray(initial_cov, dtype=np.float64).copy()  # its covariance (before it: the start's)
        self.start: np.ndarray | None = None  # the first key scan's position (m, map frame)
        # per key scan added, row by row: pose (3), covariance (9, row-major), path length from the first (m)
        self._history = np.zeros((256, 13))
        self._n = 0
        self._jumps = np.zeros((3, 3))  # the relocalisations' translations, summed (map frame)
        self.revisits = 0  # key scans placed against older map

    def __len__(self) -> int:
        """Key scans added: the index the next one gets."""
        return self._n

    def add(self, key: KeyScan) -> None:
        """Compound the step to a new key scan."""
        path = 0.0
        if self.key is not None:
            cfg = self.config
            step = (cfg.scaled(cfg.step_covariance(self.key, key), partial_step(self.key, key))
                    + cfg.jump_covariance(self.key, key))
            self.cov = compose_covariance(self.key.pose, relative(self.key.pose, key.pose), self.cov, step)
            if key.jump is not None:  # (the step's jump term in the map frame)
                self._jumps = self._jumps + jump_translation(key)
            path = self._history[self._n - 1, 12] + float(np.hypot(*(key.pose[:2] - self.key.pose[:2])))
            revisit = self._revisit_covariance(key, path)
            if revisit is not None:
                try:
                    self.cov = psd_min(self.cov - self._jumps, revisit) + self._jumps
                    self.revisits += 1
                except np.linalg.LinAlgError:  # the chain's part not positive definite: keep the step's
                    pass
        else:
            self.start = np.asarray(key.pose[:2], dtype=np.float64).copy()
        self.key = key
        if self._n == len(self._history):
            self._history = np.concatenate([self._history, np.zeros_like(self._history)])
        self._history[self._n] = np.concatenate([np.asarray(key.pose, dtype=np.float64), self.cov.ravel(), [path]])
        self._n += 1

    def _revisit_covariance(self, key: KeyScan, path: float) -> np.ndarray | None:
        """The covariance of ``key`` placed against the older map its match landed on, or None when it did
        not come back onto older map (see the class)."""
        cfg = self.config
        if cfg.revisit_gap <= 0 or key.anchors is None or key.jump is not None:
            return None
        a = np.asarray(key.anchors, dtype=np.int64)
        a = a[(a >= 0) & (a < self._n)]
        if a.size == 0:
            return None
        owners, counts = np.unique(a, return_counts=True)
        rows = self._history[owners]
        d = np.asarray(key.pose[:2], dtype=np.float64) - rows[:, :2]
        old = rows[:, 12] + np.hypot(d[:, 0], d[:, 1]) + cfg.revisit_gap < path
        if counts[old].sum() < cfg.revisit_share * a.size:
            return None
        # each anchor's covariance carried to this pose (the map it placed, seen from here), weighted by points
        w = counts[old] / counts[old].sum()
        j = np.zeros((int(old.sum()), 3, 3))
        j[:, 0, 0] = j[:, 1, 1] = j[:, 2, 2] = 1.0
        j[:, 0, 2] = -d[old, 1]
        j[:, 1, 2] = d[old, 0]
        covs = rows[old, 3:12].reshape(-1, 3, 3)
        mean = np.tensordot(w, j @ covs @ j.transpose(0, 2, 1), axes=1)
        out = mean + np.asarray(key.cov, dtype=np.float64)
        if key.constrained is not None:  # a partial match: the older map bounds only what it constrained
            _, _, vt = np.linalg.svd(key.constrained)
            free = vt[len(key.constrained):]
            out = out + _UNBOUNDED * free.T @ free
        return out

    def covariance_at(self, pose: np.ndarray, stamp: float) -> np.ndarray:
        """Covariance (3, 3) of the front end's pose ``pose`` (base, map frame) at ``stamp`` (s)."""
        if self.key is None:
            return self.cov.copy()
        cov = self.config.carried(self.key.pose, self.cov, relative(self.key.pose, pose), stamp - self.key.stamp)
        k = self.config.scale_sigma
        if k > 0.0:  # (the outer product of d, element by element)
            dx, dy = k * (float(pose[0]) - float(self.start[0])), k * (float(pose[1]) - float(self.start[1]))
            cov[0, 0] += dx * dx
            cov[0, 1] += dx * dy
            cov[1, 0] += dy * dx
            cov[1, 1] += dy * dy
        return cov
