"""The SLAM back end: key scans from the front end -> pose graph + submaps + loop closure.

The front end (:class:`~glassmap.pose.estimator.PoseEstimator`) keeps matching every scan against the map it
builds; the back end takes each key scan it hands over (``PoseEstimator.last_key_scan``) and

* appends a node to the :class:`~glassmap.pose.graph.PoseGraph` with a *sequential* edge from the previous
  key scan: the front end's relative pose, with the covariance of :mod:`glassmap.pose.chain` (odometry, fused
  with the matches where both key scans were matched, scaled by ``chain_scale``, plus the jump where the front
  end relocalised after a lost track), so that without closures the graph's marginal is the front end's own
  reported covariance;
* files it into the open :class:`~glassmap.pose.submaps.Submap`;
* every few key scans asks the :class:`~glassmap.pose.loop_closure.LoopCloser` for closures against older
  submaps and adds the accepted ones as *loop* edges (iSAM2 re-solves). Before that, each closure is compared
  with the front end's own relative pose between its two nodes, whose covariance is the scaled chain's between
  them: a front end that drifted more than ``chain_scale`` allows (a steady turn, a slide along a corridor)
  fails this test (squared Mahalanobis distance above the chi-square ``chain_gate`` point), and the
  sequential edges between the two nodes get their unscaled covariance back (the graph is solved again), so
  that the closure's correction is spread along them as a random walk instead of bending the stiff chain.

The corrected pose of anything the front end places is the front-end pose moved by the correction of the newest
node (graph solution (+) front-end pose^-1); :func:`corrected_estimate` gives it with its covariance from the
graph (``latest``). The back end is pure computation; the runtime runs it in a
worker process (``runtime.graph_worker``) so no scan waits for it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from glassmap.grid import OccupancyGrid, OccupancyParams
from glassmap.mapping import GlassMapper, MapperConfig
from glassmap.pose.chain import ChainConfig, partial_step
from glassmap.pose.corrected import MapRebuild, rebuild_maps
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.loop_closure import LoopCloser, LoopClosureConfig
from glassmap.pose.motion import compose, compose_covariance, compose_jacobians, relative
from glassmap.pose.submaps import SubmapConfig, SubmapStore
from glassmap.types import PoseEstimate, wrap_angle

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BackEndConfig:
    """chain: the sequential edges' covariance (:class:`~glassmap.pose.chain.ChainConfig`); chain_gate: the
    chi-square probability beyond which a closure disagrees with the scaled chain (then unscaled between its
    nodes); loop_closure: on/off and its settings; shared_closure_error: once the graph holds a closure, the
    corrected estimate's covariance also carries the closures' floor (``closure.cov_floor``, the submap's own
    error) once: the closures against one submap share that error, and the graph, which takes each closure as
    independent, divides it by their number; submaps."""

    chain: ChainConfig = field(default_factory=ChainConfig)
    chain_gate: float = 0.99
    loop_closure: bool = True
    shared_closure_error: bool = True
    closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    submaps: SubmapConfig = field(default_factory=SubmapConfig)

    def __post_init__(self) -> None:
        if not 0.0 < self.chain_gate < 1.0:
            raise ValueError(f"chain_gate is a chi-square probability in (0, 1), got {self.chain_gate}")


@dataclass(frozen=True)
class Closure:
    """An accepted loop closure: key scan ``node`` at ``pose`` (3,) in the frame of node ``anchor``; ``proj``
    (3, 3) projects onto the directions it constrains (the identity where it constrains all three)."""

    anchor: int
    node: int
    pose: np.ndarray
    cov: np.ndarray
    stamp: float
    proj: np.ndarray = field(default_factory=lambda: np.eye(3))

    def error(self, truth_anchor: np.ndarray, truth_node: np.ndarray) -> tuple[float, float]:
        """(m, rad) the closure's error against the true poses of its two nodes, in the directions it
        constrains."""
        e = relative(truth_anchor, truth_node) - self.pose
        e[2] = float(wrap_angle(e[2]))
        e = self.proj @ e
        return float(np.hypot(e[0], e[1])), abs(float(e[2]))


@dataclass(frozen=True)
class GraphCorrection:
    """The pose graph's word on the front end's poses after its newest node: ``correction`` (3,), the rigid
    transform taking front-end poses near that node to the corrected frame (:meth:`GraphBackEnd.correction`);
    the node's front-end pose ``front`` (3,, base, map frame) and ``stamp`` (s); ``cov`` (3, 3) its marginal
    covariance in the graph (map frame, x, y, yaw: :meth:`~glassmap.pose.graph.PoseGraph.newest_covariance`),
    and the loop closures accepted up to it."""

    correction: np.ndarray
    front: np.ndarray
    stamp: float
    cov: np.ndarray
    closures: int


def corrected_estimate(est: PoseEstimate, corr: GraphCorrection | None, config: BackEndConfig,
                       off_chain: np.ndarray | None = None) -> PoseEstimate:
    """A front-end estimate (base pose, map frame) moved by the pose graph's correction: the newest node's
    optimised pose composed with the front end's motion since that node. Its covariance is the node's
    marginal carried along that motion, plus the motion's own odometry noise (:meth:`ChainConfig.carried`), plus
    the closures' shared error (``BackEndConfig.shared_closure_error``; x and y equal, so in any frame), plus
    ``off_chain`` turned with the correction: what the front end's covariance holds beyond its chain of key
    scans (``PoseEstimator.off_chain_covariance``: a pose held past the extrapolation limit, a lost track's
    widened covariance).
    ``corr`` None (the graph holds no node yet): ``est`` unchanged."""
    if corr is None:
        return est
    node = compose(corr.correction, corr.front)
    cov = config.chain.carried(node, corr.cov, relative(corr.front, est.pose), est.stamp - corr.stamp)
    if corr.closures and config.shared_closure_error:
        cov = cov + np.diag(np.square(config.closure.cov_floor))
    if off_chain is not None:
        _, turn = compose_jacobians(corr.correction, est.pose)
        cov = cov + turn @ np.asarray(off_chain, dtype=np.float64) @ turn.T
    x, y, yaw = compose(corr.correction, est.pose)
    return PoseEstimate(est.stamp, float(x), float(y), float(yaw), 0.5 * (cov + cov.T), est.status)


class GraphBackEnd:
    """Pose graph over the front end's key scans, with loop closure (see the module docstring)."""

    def __init__(self, config: BackEndConfig = BackEndConfig(), sigma_hit: float = 0.03) -> None:
        self.config = config
        self.graph = None  # the PoseGraph, from the first key scan (gtsam is imported then: not by the config)
        self.submaps = SubmapStore(config.submaps)
        self.closer = LoopCloser(config.closure, sigma_hit)
        self.keys: list[KeyScan] = []
        self.travel: list[float] = []  # path length (m) at each node, from the front-end poses
        self.closures: list[Closure] = []
        self.seq_cov: list[np.ndarray] = []  # sequential edges' covariances before chain_scale
        self.jump_cov: list[np.ndarray] = []  # and what a relocalisation adds to them (ChainConfig.jump_covariance)
        self.unscaled: list[bool] = []  # per sequential edge: chain_scale taken off by a closure
        self.partial: list[bool] = []  # per sequential edge: a key scan at either end matched in < 3 directions
        self.chain_unscaled = 0  # closures that took chain_scale off the edges between their nodes
        from scipy.stats import chi2

        self._chain_gate = {d: float(chi2.ppf(config.chain_gate, d)) for d in (1, 2, 3)}  # by directions

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: KeyScan) -> list[Closure]:
        """Add one key scan; returns the loop closures accepted with it."""
        if self.graph is None:
            from glassmap.pose.graph import PoseGraph

            self.graph = PoseGraph(key.pose, np.diag([1e-6, 1e-6, 1e-6]))
            node = 0
            self.travel.append(0.0)
        else:
            prev = self.keys[-1]
            rel = relative(prev.pose, key.pose)
            self.seq_cov.append(self.config.chain.step_covariance(prev, key))
            self.jump_cov.append(self.config.chain.jump_covariance(prev, key))
            self.unscaled.append(False)
            self.partial.append(partial_step(prev, key))
            node = self.graph.add_node(rel, self._scaled(len(self.seq_cov) - 1))
            self.travel.append(self.travel[-1] + float(np.hypot(rel[0], rel[1])))
        self.keys.append(key)
        self.submaps.add(node, key, self.travel[-1])
        if not self.config.loop_closure or node % self.config.closure.check_every:
            return []
        new = self.closer.check(self.submaps, self.graph.poses, node, key, self.travel[-1])
        out = []
        for c in new:
            self._check_chain(c.anchor, c.node, c.pose, c.cov, c.proj)
            self.graph.add_loop(c.anchor, c.node, c.pose, c.cov)
            out.append(Closure(c.anchor, c.node, c.pose, c.cov, self.keys[c.node].stamp, c.proj))
        if out:
            self.submaps.clear_cache()
        self.closures.extend(out)
        return out

    def _scaled(self, i: int) -> np.ndarray:
        """Covariance (3, 3) of sequential edge i (node i -> i + 1) as the graph holds it."""
        if self.unscaled[i]:
            return self.seq_cov[i] + self.jump_cov[i]
        return self.config.chain.scaled(self.seq_cov[i], self.partial[i]) + self.jump_cov[i]

    def chain_covariance(self, a: int, b: int) -> np.ndarray:
        """Covariance (3, 3) of the front end's relative pose of node b in node a's frame (a < b) that the
        sequential edges between them imply, compounded as the graph holds them."""
        cov, rel = np.zeros((3, 3)), np.zeros(3)
        for i in range(a, b):  # hundreds of 3x3 steps, once per accepted closure
            e = relative(self.keys[i].pose, self.keys[i + 1].pose)
            cov = compose_covariance(rel, e, cov, self._scaled(i))
            rel = compose(rel, e)
        return cov

    def _check_chain(self, a: int, b: int, pose: np.ndarray, cov: np.ndarray, proj: np.ndarray) -> None:
        """Unscale the sequential edges between nodes a < b when the closure (node b at ``pose`` in a's
        frame, ``cov``, constraining ``proj``) disagrees with the front end's chain between them."""
        if all(self.unscaled[a:b]):
            return
        r = np.asarray(pose, dtype=np.float64) - relative(self.keys[a].pose, self.keys[b].pose)
        r[2] = float(wrap_angle(r[2]))
        total = proj @ (self.chain_covariance(a, b) + cov) @ proj.T
        d2 = float(r @ proj.T @ np.linalg.pinv(total) @ proj @ r)
        gate = self._chain_gate[int(round(np.trace(proj)))]
        if d2 <= gate:
            return
        log.info("loop closure %d -> %d disagrees with the front end's chain between them (squared distance %.1f > "
                 "%.1f): the chain's %d edges there are taken as a random walk", a, b, d2, gate, b - a)
        self.unscaled[a:b] = [True] * (b - a)
        self.chain_unscaled += 1
        self.graph.reweight([self._scaled(i) for i in range(len(self.seq_cov))])

    def poses(self, refresh: bool = True) -> np.ndarray:
        """(N, 3) optimised key-scan poses (base, map frame). refresh=False: the solution as of the last
        loop closure (or read-back), the newest nodes chained on it, without handing iSAM2 the pending batch:
        reading it changes nothing in the graph, so when it is read does not matter to the final solution."""
        if self.graph is None:
            return np.zeros((0, 3))
        return self.graph.refresh() if refresh else self.graph.poses

    def correction(self) -> np.ndarray:
        """(3,) the rigid transform taking front-end poses near the newest key scan to the corrected frame."""
        if self.graph is None:
            return np.zeros(3)
        last = self.graph.poses[-1]
        front = self.keys[-1].pose
        return compose(last, relative(front, np.zeros(3)))

    def latest(self) -> GraphCorrection | None:
        """The correction after the newest node with that node's marginal (:class:`GraphCorrection`); None
        before the first key scan."""
        if self.graph is None:
            return None
        key = self.keys[-1]
        return GraphCorrection(self.correction(), key.pose.copy(), key.stamp, self.graph.newest_covariance(),
                               len(self.closures))

    def stamps(self) -> np.ndarray:
        """(N,) stamps (s) of the key scans (the nodes)."""
        return np.array([k.stamp for k in self.keys])

    def corrected_maps(self, params: OccupancyParams = OccupancyParams(), resolution: float = 0.05,
                       poses: np.ndarray | None = None, mapper: MapperConfig | None = None
                       ) -> tuple[OccupancyGrid, GlassMapper | None]:
        """The maps that follow the corrected trajectory: every key scan re-integrated at its optimised pose
        (``poses``, default the current solution); see :func:`glassmap.pose.corrected.rebuild_maps`."""
        poses = self.poses() if poses is None else poses
        return rebuild_maps(self.keys, poses, params, resolution, mapper)

    def map_rebuild(self, params: OccupancyParams = OccupancyParams(), resolution: float = 0.05,
                    poses: np.ndarray | None = None, mapper: MapperConfig | None = None) -> MapRebuild:
        """:meth:`corrected_maps` to build a few key scans at a time (:class:`~glassmap.pose.corrected.MapRebuild`);
        key scans added after this call are not in it."""
        return MapRebuild(self.keys, self.poses() if poses is None else poses, params, resolution, mapper)
