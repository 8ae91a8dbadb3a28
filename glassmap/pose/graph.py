"""Pose graph of key scans on gtsam's iSAM2: sequential edges, loop-closure edges, incremental updates.

Nodes are key-scan base poses (x, y m, yaw rad) in the map frame. Node 0 carries a prior (the map frame's
anchor). Edges are relative poses ``relative(a, b)`` (b in a's frame, :func:`glassmap.pose.motion.relative`)
with a 3x3 covariance of that relative pose's (x, y, yaw) components; gtsam expects the covariance in the
tangent space of Pose2 at the measurement (x, y rotated into b's frame), which :func:`to_tangent` converts
to. Sequential edges go to iSAM2 in batches of ``batch`` (one update each; the solution of the newest nodes
is their chained guess until then); a loop closure flushes the batch, is one update, and is followed by
extra iterations (:meth:`PoseGraph.add_loop`) so the correction is fully propagated.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from glassmap.pose.motion import compose, compose_covariance, compose_jacobians


class PoseGraphError(RuntimeError):
    """An edge refers to a node that does not exist, or the solver failed."""


@dataclass(frozen=True)
class Edge:
    """One edge: from node a to node b, relative pose (3,) of b in a's frame, covariance (3, 3) of its
    (x, y, yaw) components, kind: "sequential" or "loop"."""

    a: int
    b: int
    rel: np.ndarray
    cov: np.ndarray
    kind: str


def to_tangent(rel: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance of a relative pose's (x, y, yaw) components -> that of gtsam's Pose2 local coordinates
    at ``rel`` (rel composed with Exp(xi): the translation part of xi is in the frame of rel's end)."""
    c, s = np.cos(rel[2]), np.sin(rel[2])
    g = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out = g @ cov @ g.T
    return 0.5 * (out + out.T)


def _noise(cov: np.ndarray):
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=np.float64))


class PoseGraph:
    """Key-scan poses, their edges, and the iSAM2 solution (``poses``, ``marginal``)."""

    def __init__(self, first_pose: np.ndarray, first_cov: np.ndarray, loop_iterations: int = 3,
                 batch: int = 10) -> None:
        self.loop_iterations = loop_iterations
        self.batch = batch  # sequential edges handed to iSAM2 together (one update per batch)
        self._first_cov = np.asarray(first_cov, dtype=np.float64).copy()
        self.edges: list[Edge] = []
        self._poses = np.asarray(first_pose, dtype=np.float64).reshape(1, 3).copy()
        self._start()

    def _start(self) -> None:
        """A new iSAM2 holding the prior on node 0 only."""
        self._held = None  # (node, its map-frame marginal) of the newest node iSAM2 holds (newest_covariance)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.001)
        params.relinearizeSkip = 1
        params.setFactorization("QR")  # robust to the poorly conditioned long chains of tight odometry edges
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._poses[0]), _noise(self._first_cov)))
        v = gtsam.Values()
        v.insert(0, gtsam.Pose2(*self._poses[0]))
        self._isam.update(g, v)

    def __len__(self) -> int:
        return self._poses.shape[0]

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) the current solution (a copy)."""
        return self._poses.copy()

    def add_node(self, rel: np.ndarray, cov: np.ndarray) -> int:
        """Append a node at ``rel`` (relative pose, (3,)) from the last node with covariance ``cov`` (3, 3) of
        rel's (x, y, yaw); returns its index."""
        a = len(self) - 1
        b = a + 1
        rel = np.asarray(rel, dtype=np.float64)
        self._new_factors.add(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(*rel), _noise(to_tangent(rel, cov))))
        guess = compose(self._poses[a], rel)
        self._new_values.insert(b, gtsam.Pose2(*guess))
        self.edges.append(Edge(a, b, rel.copy(), np.asarray(cov, dtype=np.float64).copy(), "sequential"))
        self._poses = np.vstack([self._poses, guess])
        if self._new_values.size() >= self.batch:
            self._flush()
        if len(self.edges) % 50 == 0:  # the chain alone changes little: read the solution back now and then
            self._read()
        return b

    def _flush(self) -> None:
        """Hand the buffered sequential edges to iSAM2 (one update)."""
        if self._new_values.size():
            self._isam.update(self._new_factors, self._new_values)
            self._held = None
            self._new_factors = gtsam.NonlinearFactorGraph()
            self._new_values = gtsam.Values()

    def add_loop(self, a: int, b: int, rel: np.ndarray, cov: np.ndarray) -> None:
        """Add a loop-closure edge (node b at ``rel`` in node a's frame, covariance ``cov``) and re-solve."""
        n = len(self)
        if not (0 <= a < n and 0 <= b < n) or a == b:
            raise PoseGraphError(f"loop edge {a} -> {b} needs two different existing nodes (0..{n - 1})")
        rel = np.asarray(rel, dtype=np.float64)
        self._flush()
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(*rel), _noise(to_tangent(rel, cov))))
        self.edges.append(Edge(a, b, rel.copy(), np.asarray(cov, dtype=np.float64).copy(), "loop"))
        self._isam.update(g, gtsam.Values())
        for _ in range(self.loop_iterations):
            self._isam.update()
        self._held = None
        self._read()

    def reweight(self, sequential_covs: list[np.ndarray]) -> None:
        """Give the sequential edges new covariances (one (3, 3) per sequential edge, in order) and solve the
        whole graph again from the current solution (one batch update: used rarely, not per key scan)."""
        seq = [i for i, e in enumerate(self.edges) if e.kind == "sequential"]
        if len(sequential_covs) != len(seq):
            raise PoseGraphError(f"{len(sequential_covs)} covariances for {len(seq)} sequential edges")
        for i, cov in zip(seq, sequential_covs):
            e = self.edges[i]
            self.edges[i] = Edge(e.a, e.b, e.rel, np.asarray(cov, dtype=np.float64).copy(), e.kind)
        self._flush()
        guess = self._isam.calculateEstimate()
        self._start()
        g = gtsam.NonlinearFactorGraph()
        for e in self.edges:
            g.add(gtsam.BetweenFactorPose2(e.a, e.b, gtsam.Pose2(*e.rel), _noise(to_tangent(e.rel, e.cov))))
        v = gtsam.Values()
        for i in range(1, len(self)):
            v.insert(i, guess.atPose2(i))
        self._isam.update(g, v)
        for _ in range(self.loop_iterations):
            self._isam.update()
        self._read()

    def _read(self) -> None:
        self._flush()
        est = self._isam.calculateEstimate()
        n = len(self)
        out = np.empty((n, 3))
        for i in range(n):  # N small objects; called after loop closures and every 50 nodes, not per scan
            p = est.atPose2(i)
            out[i] = (p.x(), p.y(), p.theta())
        self._poses = out

    def refresh(self) -> np.ndarray:
        """Read the full solution back from iSAM2 and return it (N, 3)."""
        self._read()
        return self.poses

    def marginal(self, i: int) -> np.ndarray:
        """Marginal covariance (3, 3) of node i in its own tangent space (x, y in the node's frame, yaw)."""
        if not 0 <= i < len(self):
            raise PoseGraphError(f"no node {i} (0..{len(self) - 1})")
        self._flush()
        return np.asarray(self._isam.marginalCovariance(i))

    def newest_covariance(self) -> np.ndarray:
        """Marginal covariance (3, 3) of the newest node in the map frame (x, y, yaw): iSAM2's marginal of the
        newest node it holds, compounded along the sequential edges not yet handed to it (they form a chain
        from that node, so this is its marginal to first order). Leaves the pending batch where it is, so
        reading it does not change the solution."""
        pending = self._new_values.size()
        k = len(self) - 1 - pending
        if self._held is None or self._held[0] != k:
            _, rot = compose_jacobians(self._poses[k], np.zeros(3))  # node frame -> map frame
            self._held = (k, rot @ np.asarray(self._isam.marginalCovariance(k)) @ rot.T)
        cov = self._held[1]
        for e in self.edges[len(self.edges) - pending:]:  # at most one batch of sequential edges
            cov = compose_covariance(self._poses[e.a], e.rel, cov, e.cov)
        return 0.5 * (cov + cov.T)
