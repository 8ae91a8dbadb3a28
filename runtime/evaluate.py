"""Score an online glass confidence map against a simulated world's blueprint (docs/method.md section 6).

Same rules as the paper's experiment in :mod:`glassmap.eval.trial`: the blueprint's wall/glass cells that
were seen (hit by at least one returned beam, from the simulator's truth) and lie within ``eval_radius`` of
a glass cell are evaluated; a cell is correct when its map label (``GlassMap.labels``: glass, not glass,
undecided, not occupied) agrees with the blueprint; undecided, not occupied or never registered count as
errors. The score is :func:`glassmap.eval.metrics.score_map`.

``seen`` comes from the emulated devices (:mod:`runtime.devices` records the blueprint cells the simulated
laser hit); without it the cells the map observed (known in the occupancy grid) stand in for it.
``tolerance`` > 0 lets a blueprint cell take the label of the nearest occupied map cell within that many
cells (0, the default, is the paper's per-cell rule).

An online map is built from estimated poses, so it sits a few centimetres off the blueprint (the pose
estimator's drift), and the per-cell rule then counts a well-labelled but shifted wall as unregistered.
:func:`evaluate_map` therefore also reports an ``aligned`` score: the map shifted by the whole-cell offset
(at most ``max_shift`` cells each way) that best overlays its occupied cells on the blueprint's walls, and
scored with a one-cell tolerance. Both are printed; the strict one is the paper's rule.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from glassmap.eval.metrics import MapScore, score_map


@dataclass
class MapEvaluation(MapScore):
    """A :class:`MapScore` (strict per-cell rule) plus where ``seen`` came from and the aligned score."""

    seen_from: str = "simulator"
    aligned: MapScore | None = None
    shift_cells: tuple[int, int] = (0, 0)

    def describe(self) -> str:
        text = (f"classification error against the blueprint (per cell, paper rule): {100 * self.error:.1f} % of "
                f"{self.n_cells} wall/glass cells near glass ({self.n_glass} glass, {self.n_wall} wall); glass recall "
                f"{100 * self.glass_recall:.1f} %, false glass on walls {100 * self.false_glass_rate:.1f} %, "
                f"unregistered or undecided {100 * self.unregistered:.1f} %")
        if self.aligned is not None:
            a = self.aligned
            text += (f"\nclassification error after aligning the map to the blueprint (shift {self.shift_cells} cells, "
                     f"1-cell tolerance): {100 * a.error:.1f} %; glass recall {100 * a.glass_recall:.1f} %, false glass "
                     f"on walls {100 * a.false_glass_rate:.1f} %, unregistered or undecided {100 * a.unregistered:.1f} %")
        return text


def _on_grid(arr: np.ndarray, origin: np.ndarray, target_origin: np.ndarray, shape: tuple[int, int],
             resolution: float, fill) -> np.ndarray:
    """``arr`` (grid with corner ``origin``) cut / padded onto a grid with corner ``target_origin``, ``shape``."""
    out = np.full(shape, fill, dtype=arr.dtype)
    off = np.rint((np.asarray(target_origin) - np.asarray(origin)) / resolution).astype(int)  # (x, y) cells
    h, w = shape
    y0, x0 = max(0, -off[1]), max(0, -off[0])
    y1, x1 = min(h, arr.shape[0] - off[1]), min(w, arr.shape[1] - off[0])
    if y1 > y0 and x1 > x0:
        out[y0:y1, x0:x1] = arr[y0 + off[1]:y1 + off[1], x0 + off[0]:x1 + off[0]]
    return out


def _within(labels: np.ndarray, tolerance: int) -> np.ndarray:
    """Each cell takes the label of the nearest occupied cell (label > -2) within ``tolerance`` cells."""
    occ = labels > -2
    if tolerance <= 0 or not occ.any():
        return labels
    dist, (iy, ix) = ndimage.distance_transform_edt(~occ, return_indices=True)
    return np.where(dist <= tolerance, labels[iy, ix], labels).astype(np.int8)


def best_shift(labels: np.ndarray, blueprint_labels: np.ndarray, max_shift: int) -> tuple[int, int]:
    """Whole-cell (dx, dy) that best overlays the occupied map cells on the blueprint's walls and glass."""
    occ, walls = labels > -2, blueprint_labels > 0
    best, best_score = (0, 0), -1
    for dy in range(-max_shift, max_shift + 1):
        rolled = np.roll(occ, dy, axis=0)
        for dx in range(-max_shift, max_shift + 1):
            score = int(np.count_nonzero(np.roll(rolled, dx, axis=1) & walls))
            if score > best_score or (score == best_score and abs(dx) + abs(dy) < abs(best[0]) + abs(best[1])):
                best, best_score = (dx, dy), score
    return best


def evaluate_map(maps, world, *, seen: np.ndarray | None = None, eval_radius: float = 1.5,
                 tolerance: int = 0, max_shift: int = 4) -> MapEvaluation:
    """Score ``maps`` (anything with ``grid``, ``occupancy`` and ``glass``: the runtime's
    :class:`~glassmap.mapping.GlassMapper`, or a :class:`~glassmap.mapping.MapCopy` such as the pose graph's
    corrected maps) against ``world``.

    seen: (H, W) bool on ``Blueprint.from_world(world, resolution)``'s grid, or None (see module docstring).
    max_shift: cells searched each way for the aligned score (0 = no aligned score)."""
    from glassmap.eval.trial import evaluation_mask
    from glassmap.sim.blueprint import Blueprint

    g = maps.grid
    bp = Blueprint.from_world(world, resolution=g.resolution)
    labels = maps.glass.labels(maps.occupancy)
    raw = _on_grid(labels, g.origin, bp.origin, bp.labels.shape, g.resolution, np.int8(-2))
    lab = _within(raw, tolerance)
    seen_from = "simulator"
    if seen is None or seen.shape != bp.labels.shape:
        known = _on_grid(~maps.occupancy.unknown(), g.origin, bp.origin, bp.labels.shape, g.resolution, False)
        seen = ndimage.binary_dilation(known, iterations=2)
        seen_from = "map"
    mask = evaluation_mask(bp.labels, seen, bp.resolution, eval_radius)
    result = MapEvaluation(**vars(score_map(lab, bp.labels, mask)), seen_from=seen_from)
    if max_shift > 0:
        dx, dy = best_shift(raw, bp.labels, max_shift)
        shifted = _within(np.roll(np.roll(raw, dy, axis=0), dx, axis=1), max(tolerance, 1))
        result.aligned = score_map(shifted, bp.labels, mask)
        result.shift_cells = (dx, dy)
    return result


@dataclass
class TrajectoryEvaluation:
    """Estimated poses against the true poses of the same scans (map frame = world frame, metres, radians).

    final_*: at the last processed scan; ate: absolute trajectory error, the RMS of the position errors over
    all processed scans (no alignment: the estimate starts from the true start pose); max_error: the largest
    position error; yaw_rms: RMS heading error; n: scans scored (those with a true pose)."""

    n: int
    ate: float
    max_error: float
    yaw_rms: float
    final_error: float
    final_true: np.ndarray
    final_estimate: np.ndarray

    def describe(self) -> str:
        t, e = self.final_true, self.final_estimate
        return (f"final pose (last processed scan): true ({t[0]:.2f}, {t[1]:.2f}) m, estimated ({e[0]:.2f}, "
                f"{e[1]:.2f}) m, error {100 * self.final_error:.1f} cm\n"
                f"trajectory error over {self.n} scans: ATE (RMS) {100 * self.ate:.1f} cm, max "
                f"{100 * self.max_error:.1f} cm, heading RMS {np.degrees(self.yaw_rms):.2f} deg")


def _truth_at(keys: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(hit (N,) bool, rows (N, 4)): for each stamp key, whether ``truth`` (m, 4: stamp key, x, y, yaw) has
    it, and that row (any row where not)."""
    keys = np.asarray(keys, np.float64).reshape(-1)
    tru = np.asarray(truth, np.float64).reshape(-1, 4)
    if not len(tru):
        return np.zeros(len(keys), dtype=bool), np.zeros((len(keys), 4))
    order = np.argsort(tru[:, 0], kind="stable")
    k = order[np.clip(np.searchsorted(tru[order, 0], keys), 0, len(tru) - 1)]
    return tru[k, 0] == keys, tru[k]


def evaluate_trajectory(estimates: np.ndarray, truth: np.ndarray) -> TrajectoryEvaluation | None:
    """Score estimates (n, 4: sensor stamp ms (24-bit), x, y, yaw) against ``truth`` (m, 4: the same columns,
    :class:`runtime.devices.TruthLog`) at the same scans, matched by stamp; None if no scan matches."""
    est = np.asarray(estimates, np.float64).reshape(-1, 4)
    hit, at = _truth_at(est[:, 0], truth)
    if not hit.any():
        return None
    e, t = est[hit], at[hit]
    d = np.hypot(e[:, 1] - t[:, 1], e[:, 2] - t[:, 2])
    dyaw = np.angle(np.exp(1j * (e[:, 3] - t[:, 3])))
    return TrajectoryEvaluation(n=int(hit.sum()), ate=float(np.sqrt(np.mean(d ** 2))), max_error=float(d.max()),
                                yaw_rms=float(np.sqrt(np.mean(dyaw ** 2))), final_error=float(d[-1]),
                                final_true=t[-1, 1:].copy(), final_estimate=e[-1, 1:].copy())


CLOSURE_COLUMNS = ["anchor", "node", "anchor_stamp", "node_stamp", "directions", "error_xy", "error_yaw", "false"]
"""Columns of a closure row: its two key scans (graph nodes) and their stamps (s, host), the directions of
pose space it constrains (3, or 2 in a corridor), its error against the truth in those directions (m, rad)
and whether that makes it false (more than ``FALSE_CLOSURE_XY`` or ``FALSE_CLOSURE_YAW``)."""


@dataclass(frozen=True)
class GraphEvaluation:
    """The pose graph's result against the truth (runtime demo with loop closure): ate (m), the RMS position
    error of the optimised key-scan poses over the n key scans matched to a true pose; closures scored (both
    nodes matched), false: those more than ``FALSE_CLOSURE_XY`` / ``FALSE_CLOSURE_YAW`` off the truth in the
    directions they constrain (:meth:`glassmap.pose.backend.Closure.error`), worst_xy / worst_yaw (m, rad):
    the largest closure errors; rows: one per closure scored (:data:`CLOSURE_COLUMNS`)."""

    n: int
    ate: float
    rows: list[dict] = field(default_factory=list)

    @property
    def closures(self) -> int:
        return len(self.rows)

    @property
    def false(self) -> int:
        return sum(r["false"] for r in self.rows)

    @property
    def worst_xy(self) -> float:
        return max((r["error_xy"] for r in self.rows), default=0.0)

    @property
    def worst_yaw(self) -> float:
        return max((r["error_yaw"] for r in self.rows), default=0.0)

    def write_csv(self, path: str | Path) -> None:
        """Every closure scored, one row each (:data:`CLOSURE_COLUMNS`), to a CSV file."""
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CLOSURE_COLUMNS)
            w.writeheader()
            w.writerows(self.rows)

    def describe(self) -> str:
        out = f"optimised key-scan trajectory: ATE (RMS) {100 * self.ate:.1f} cm over {self.n} key scans; "
        if not self.closures:
            return out + "no loop closure to score against the truth"
        return out + (f"{self.closures} loop closures scored against the truth, {self.false} false (worst "
                      f"{100 * self.worst_xy:.1f} cm, {np.degrees(self.worst_yaw):.2f} deg where they constrain)")


def evaluate_graph(keys: np.ndarray, poses: np.ndarray, accepted, truth: np.ndarray,
                   stamps: np.ndarray | None = None) -> GraphEvaluation | None:
    """Score the optimised key-scan ``poses`` (N, 3) and the ``accepted`` closures (their nodes index the
    key scans) against ``truth`` (m, 4: stamp key, x, y, yaw, as in :func:`evaluate_trajectory`); ``keys``
    (N,) are the key scans' stamp keys in the same unit (NaN where unknown), ``stamps`` (N,) their stamps
    (s, for the closure rows; NaN if not given). None if no key scan matches."""
    from glassmap.pose.evaluate import FALSE_CLOSURE_XY, FALSE_CLOSURE_YAW

    hit, at = _truth_at(keys, truth)
    if not hit.any():
        return None
    at = at[:, 1:]
    d = np.hypot(*(np.asarray(poses)[hit, :2] - at[hit, :2]).T)
    stamps = np.full(len(hit), np.nan) if stamps is None else np.asarray(stamps, np.float64)
    scored = [c for c in accepted if hit[c.anchor] and hit[c.node]]
    errs = np.array([c.error(at[c.anchor], at[c.node]) for c in scored]).reshape(-1, 2)
    bad = (errs[:, 0] > FALSE_CLOSURE_XY) | (errs[:, 1] > FALSE_CLOSURE_YAW)
    rows = [dict(anchor=c.anchor, node=c.node, anchor_stamp=float(stamps[c.anchor]), node_stamp=float(stamps[c.node]),
                 directions=int(round(np.trace(c.proj))), error_xy=float(e[0]), error_yaw=float(e[1]), false=bool(b))
            for c, e, b in zip(scored, errs, bad)]
    return GraphEvaluation(n=int(hit.sum()), ate=float(np.sqrt(np.mean(d ** 2))), rows=rows)
