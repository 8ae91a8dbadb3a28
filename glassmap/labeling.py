"""Per-beam glass labels for a recording from a floor plan (a world file): scan-to-plan alignment, then
ray casting of the plan from the aligned laser poses.

Alignment: each scan's laser pose (map frame) starts from the previous aligned pose moved by the odometry
between the two scans (the first from a rough initial pose, refined by a small grid search), then
point-to-line ICP against the plan's segments with a shrinking association gate and a Huber weight. A scan
whose inlier share or inlier RMS residual is poor is "doubtful": all its beams are unknown, and the next
scan starts from the odometry prediction.

Labels: a beam's first-echo range is matched against every intersection of its ray with the plan. Glass
(1): it matches only glass panes; not glass (0): it matches only other surfaces (including walls seen
through a pane); unknown (-1): no plan surface matches (clutter, people, mirror ghosts), surfaces of both
kinds match, the hit lies within ``boundary`` of a segment's end, an opaque plan surface lies in front of
the measured range, or the scan's alignment is doubtful.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .types import LaserGeometry, Scan

GLASS, NOT_GLASS, UNKNOWN = 1, 0, -1


class LabelingError(ValueError):
    """The recording cannot be aligned to the floor plan (the message says what to change)."""


@dataclass(frozen=True)
class LabelParams:
    """match_tol (m) + match_tol_rel * range: how far a measured range may lie from a plan surface to be
    attributed to it; boundary (m): hits this close to a segment's end are unknown; gates (m): ICP
    association gates per iteration (the last one repeats); min_inlier_share / max_rms (m): alignment
    quality below which a scan is doubtful; search_xy (m) / search_yaw_deg: grid search round the initial
    pose; stride: every stride-th beam is used for the alignment; point_sigma (m): point-to-line residual
    sigma; prior_xy (m) / prior_yaw (rad): sigma of the prior at the odometry prediction."""

    match_tol: float = 0.06
    match_tol_rel: float = 0.005
    boundary: float = 0.10
    gates: tuple[float, ...] = (0.6, 0.4, 0.25, 0.15, 0.1, 0.08)
    iterations: int = 12
    inlier: float = 0.08
    min_inlier_share: float = 0.5
    max_rms: float = 0.04
    max_correction: float = 0.5
    search_xy: float = 0.5
    search_yaw_deg: float = 8.0
    stride: int = 4
    point_sigma: float = 0.02
    prior_xy: float = 0.3
    prior_yaw: float = 0.1


@dataclass
class RecordingLabels:
    """Labels of a recording: ``x`` (m, k) context features of the labelled beams (glassmap.glass_features,
    known labels only), ``y`` (m,) bool glass, ``scan_index`` (m,) which scan each came from; per scan:
    ``poses`` (S, 3) aligned laser poses (map frame; m, rad), ``inlier_share`` (S,), ``rms`` (S,) m,
    ``doubtful`` (S,) bool; ``counts``: beams labelled glass / not glass / unknown."""

    x: np.ndarray
    y: np.ndarray
    scan_index: np.ndarray
    poses: np.ndarray
    inlier_share: np.ndarray
    rms: np.ndarray
    doubtful: np.ndarray
    counts: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)

    def beams(self):
        """The labelled beams as a glassmap.train.BeamSet."""
        from .train import BeamSet

        return BeamSet(self.x, self.y, np.full(self.y.shape[0], np.nan), np.zeros(self.y.shape[0], np.int64))

    def save(self, path: str | Path) -> Path:
        import json

        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(p, x=self.x, y=self.y, scan_index=self.scan_index, poses=self.poses,
                            inlier_share=self.inlier_share, rms=self.rms, doubtful=self.doubtful,
                            meta=np.array(json.dumps({"counts": self.counts, "params": self.params})))
        return p


def load_labels(path: str | Path) -> RecordingLabels:
    """Read a labels file written by :meth:`RecordingLabels.save`."""
    import json

    try:
        with np.load(path) as d:
            meta = json.loads(str(d["meta"]))
            return RecordingLabels(d["x"], d["y"].astype(bool), d["scan_index"], d["poses"], d["inlier_share"],
                                   d["rms"], d["doubtful"].astype(bool), meta.get("counts", {}),
                                   meta.get("params", {}))
    except (OSError, KeyError, ValueError) as e:
        raise LabelingError(f"{path}: not a labels file of `glassmap glass label` ({e})") from e


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose a (+) b: b expressed in a's frame, moved to a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2])])


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of b in a's frame (a (-) b)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(b[2] - a[2])])


def _wrap(a: float) -> float:
    return float(math.atan2(math.sin(a), math.cos(a)))


class PlanMatcher:
    """Point-to-line ICP of laser points against a floor plan's segments (map frame)."""

    def __init__(self, world, params: LabelParams = LabelParams()) -> None:
        self.p = params
        seg = np.asarray(world.segments, dtype=np.float64)
        self.a = seg[:, 0]
        self.e = seg[:, 1] - seg[:, 0]
        self.inv_len2 = 1.0 / np.maximum((self.e ** 2).sum(axis=1), 1e-12)

    def nearest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points q (n, 2): distance (n,), nearest point (n, 2) and unit normal (n, 2) of the nearest
        segment."""
        ax, ay, ex, ey = self.a[:, 0], self.a[:, 1], self.e[:, 0], self.e[:, 1]
        dx = q[:, 0:1] - ax
        dy = q[:, 1:2] - ay
        u = np.clip((dx * ex + dy * ey) * self.inv_len2, 0.0, 1.0)
        fx = dx - u * ex
        fy = dy - u * ey
        dist2 = fx * fx + fy * fy
        j = np.argmin(dist2, axis=1)
        rows = np.arange(q.shape[0])
        f = np.column_stack([ax[j] + u[rows, j] * ex[j], ay[j] + u[rows, j] * ey[j]])
        dist = np.sqrt(dist2[rows, j])
        ej = self.e[j] * np.sqrt(self.inv_len2[j])[:, None]
        nrm = np.column_stack([-ej[:, 1], ej[:, 0]])
        return dist, f, nrm

    def _points(self, pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return np.column_stack([pose[0] + c * pts[:, 0] - s * pts[:, 1], pose[1] + s * pts[:, 0] + c * pts[:, 1]])

    def score(self, pose: np.ndarray, pts: np.ndarray) -> tuple[float, float]:
        """(inlier share, inlier RMS (m)) of laser points ``pts`` (n, 2, laser frame) at ``pose``."""
        dist, _, _ = self.nearest(self._points(pose, pts))
        ok = dist < self.p.inlier
        if not ok.any():
            return 0.0, float("inf")
        return float(ok.mean()), float(np.sqrt(np.mean(dist[ok] ** 2)))

    def icp(self, pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Refined laser pose from ``pose``: Huber-weighted Gauss-Newton on the point-to-line residuals
        (sigma ``point_sigma``) with a Gaussian prior at ``pose`` (``prior_xy``, ``prior_yaw``), so that a
        direction the plan does not constrain (a long corridor) stays where the odometry put it."""
        p = self.p
        guess = np.asarray(pose, dtype=np.float64)
        x = guess.copy()
        prior = np.diag([1.0 / p.prior_xy ** 2, 1.0 / p.prior_xy ** 2, 1.0 / p.prior_yaw ** 2])
        inv_s2 = 1.0 / p.point_sigma ** 2
        for it in range(p.iterations):
            gate = p.gates[min(it, len(p.gates) - 1)]
            q = self._points(x, pts)
            dist, f, nrm = self.nearest(q)
            use = dist < gate
            if use.sum() < 6:
                break
            qn, fn, nn = q[use], f[use], nrm[use]
            r = ((qn - fn) * nn).sum(axis=1)
            dq = np.column_stack([-(qn[:, 1] - x[1]), qn[:, 0] - x[0]])  # d q / d yaw
            J = np.column_stack([nn[:, 0], nn[:, 1], (nn * dq).sum(axis=1)])
            k = 0.03
            w = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-12)) * inv_s2
            dx = x - guess
            dx[2] = _wrap(dx[2])
            H = J.T @ (J * w[:, None]) + prior
            step = -np.linalg.solve(H, J.T @ (w * r) + prior @ dx)
            x += step
            x[2] = _wrap(x[2])
            if np.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-5:
                break
        return x

    def search(self, pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Best pose of a grid round ``pose`` (+- search_xy, +- search_yaw_deg) by inlier share, refined."""
        p = self.p
        sub = pts[:: max(1, pts.shape[0] // 80)]
        best, best_s = np.asarray(pose, dtype=np.float64), -1.0
        steps_xy = np.arange(-p.search_xy, p.search_xy + 1e-9, 0.2)
        steps_yaw = np.radians(np.arange(-p.search_yaw_deg, p.search_yaw_deg + 1e-9, 2.0))
        for dyaw in steps_yaw:
            for dx in steps_xy:
                for dy in steps_xy:
                    cand = np.array([pose[0] + dx, pose[1] + dy, pose[2] + dyaw])
                    dist, _, _ = self.nearest(self._points(cand, sub))
                    s = float((dist < 0.15).mean())
                    if s > best_s:
                        best, best_s = cand, s
        return self.icp(best, pts)


def _scan_points(scan: Scan, stride: int) -> np.ndarray:
    r = scan.ranges
    a = scan.angles
    g = scan.geometry
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= g.range_min) & (r <= g.range_max)
    idx = np.flatnonzero(ok)[::stride]
    return np.column_stack([r[idx] * np.cos(a[idx]), r[idx] * np.sin(a[idx])])


def beam_labels(world, scan: Scan, laser_pose: np.ndarray, params: LabelParams = LabelParams()) -> np.ndarray:
    """Labels (n,) int8 of one scan's beams at an aligned laser pose: GLASS, NOT_GLASS or UNKNOWN."""
    from .sim.laser import cast_pairs

    r = scan.ranges
    n = r.shape[0]
    g = scan.geometry
    geo = LaserGeometry(n_beams=n, angle_min=g.angle_min, angle_increment=g.angle_increment,
                        range_min=g.range_min, range_max=g.range_max, scan_time=g.scan_time)
    out = np.full(n, UNKNOWN, dtype=np.int8)
    with np.errstate(invalid="ignore"):
        ranged = np.isfinite(r) & (r >= g.range_min) & (r <= g.range_max)
    if not ranged.any():
        return out
    beam, seg, t, _ = cast_pairs(world, laser_pose, geo, float(np.nanmax(np.where(ranged, r, 0.0))) + 1.0)
    rb = r[beam]
    tol = params.match_tol + params.match_tol_rel * np.nan_to_num(rb, nan=0.0, posinf=0.0)
    glass_seg = world.segment_is_glass[seg]
    with np.errstate(invalid="ignore"):
        match = ranged[beam] & (np.abs(t - rb) < tol)
        before = ranged[beam] & (t < rb - tol) & ~glass_seg  # an opaque plan surface in front of the return
    ang = laser_pose[2] + scan.angles[beam]
    hx = laser_pose[0] + t * np.cos(ang)
    hy = laser_pose[1] + t * np.sin(ang)
    ends = world.segments[seg]
    d_end = np.minimum(np.hypot(hx - ends[:, 0, 0], hy - ends[:, 0, 1]), np.hypot(hx - ends[:, 1, 0], hy - ends[:, 1, 1]))
    near_end = match & (d_end < params.boundary)
    m_glass = np.zeros(n, dtype=bool)
    m_other = np.zeros(n, dtype=bool)
    bad = np.zeros(n, dtype=bool)
    m_glass[beam[match & glass_seg]] = True
    m_other[beam[match & ~glass_seg]] = True
    bad[beam[before | near_end]] = True
    out[ranged & m_glass & ~m_other & ~bad] = GLASS
    out[ranged & m_other & ~m_glass & ~bad] = NOT_GLASS
    return out


def label_recording(world, scans: list[Scan], odom_laser_poses: np.ndarray | None, initial_laser_pose,
                    params: LabelParams = LabelParams(), angle_method: str = "split-merge",
                    progress=None) -> RecordingLabels:
    """Align every scan to the plan and label its beams.

    ``odom_laser_poses`` (S, 3): the laser pose of each scan in the odometry frame (None: no odometry, each
    scan starts from the previous one's pose); ``initial_laser_pose``: rough (x, y, yaw) of the first scan's
    laser in the plan's frame (m, rad).
    """
    from .angles import incidence_angles
    from .glass_features import scan_features

    if not scans:
        raise LabelingError("the recording has no scans")
    matcher = PlanMatcher(world, params)
    S = len(scans)
    poses = np.zeros((S, 3))
    share = np.zeros(S)
    rms = np.full(S, np.inf)
    doubtful = np.zeros(S, dtype=bool)
    xs, ys, idx = [], [], []
    counts = {"glass": 0, "not_glass": 0, "unknown": 0}
    prev = None
    for i, scan in enumerate(scans):
        pts = _scan_points(scan, params.stride)
        if prev is None:
            guess = np.asarray(initial_laser_pose, dtype=np.float64)
            pose = matcher.search(guess, pts) if pts.shape[0] >= 6 else guess
        else:
            guess = (compose(prev, relative(odom_laser_poses[i - 1], odom_laser_poses[i]))
                     if odom_laser_poses is not None else prev)
            pose = matcher.icp(guess, pts) if pts.shape[0] >= 6 else guess
        sh, rm = matcher.score(pose, pts) if pts.shape[0] >= 6 else (0.0, float("inf"))
        ok = (sh >= params.min_inlier_share and rm <= params.max_rms
              and (prev is None or np.hypot(*(pose[:2] - guess[:2])) <= params.max_correction))
        if not ok and prev is not None and pts.shape[0] >= 6:  # lost: search round the prediction
            pose = matcher.search(guess, pts)
            sh, rm = matcher.score(pose, pts)
            ok = sh >= params.min_inlier_share and rm <= params.max_rms
        if i == 0 and not ok:
            raise LabelingError(f"the first scan does not fit the floor plan near the initial pose {list(guess)} "
                                f"(inlier share {sh:.2f}, RMS {rm:.3f} m): give a closer --initial-pose "
                                "(x,y,yaw_deg of the robot in the plan's frame)")
        poses[i], share[i], rms[i], doubtful[i] = (pose if ok else guess), sh, rm, not ok
        prev = poses[i]
        n = scan.ranges.shape[0]
        if not ok or scan.intensities is None:
            counts["unknown"] += n
            continue
        lab = beam_labels(world, scan, pose, params)
        inc = incidence_angles(scan.angles, scan.ranges, angle_method)
        use = (lab != UNKNOWN) & np.isfinite(inc.incidence) & np.isfinite(scan.intensities)
        x = scan_features("context", scan.angles, scan.ranges, scan.intensities, inc, scan.echoes,
                          scan.echo_intensities)
        xs.append(x[use])
        ys.append(lab[use] == GLASS)
        idx.append(np.full(int(use.sum()), i, dtype=np.int64))
        counts["glass"] += int((lab == GLASS).sum())
        counts["not_glass"] += int((lab == NOT_GLASS).sum())
        counts["unknown"] += int((lab == UNKNOWN).sum())
        if progress is not None:
            progress.update(1)
    k = 19
    return RecordingLabels(np.concatenate(xs) if xs else np.zeros((0, k), np.float32),
                           np.concatenate(ys) if ys else np.zeros(0, bool),
                           np.concatenate(idx) if idx else np.zeros(0, np.int64), poses, share, rms, doubtful,
                           counts, asdict(params))
