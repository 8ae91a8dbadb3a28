"""Metrics: binary classifier quality (balanced accuracy, precision/recall, ROC-AUC, ECE) and the glass
map's classification error against a blueprint (docs/method.md section 6). Pure numpy."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class BinaryReport:
    """Classifier quality on labelled beams (glass = positive class).

    ece: expected calibration error (10 equal-width bins) on the natural class mix; ece_balanced: the same
    with the classes weighted equally (the Bayesian update uses outputs as likelihood ratios with prior
    0.5, so this is the calibration that matters for the map).
    """

    n: int
    n_glass: int
    balanced_accuracy: float
    precision: float
    recall: float
    roc_auc: float
    ece: float
    ece_balanced: float

    def as_dict(self) -> dict:
        return asdict(self)


def roc_auc(y: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney U with average ranks for ties); NaN if one class is absent."""
    y = np.asarray(y, dtype=bool)
    s = np.asarray(score, dtype=np.float64)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(s, kind="mergesort")
    ranks = np.empty(len(s))
    sorted_s = s[order]
    # average ranks of ties
    _, first, counts = np.unique(sorted_s, return_index=True, return_counts=True)
    avg = first + (counts - 1) / 2.0 + 1.0
    ranks[order] = np.repeat(avg, counts)
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def expected_calibration_error(y: np.ndarray, p: np.ndarray, bins: int = 10,
                               weights: np.ndarray | None = None) -> float:
    """Weighted mean |accuracy - confidence| over equal-width bins of p(glass) (reliability of p)."""
    y = np.asarray(y, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    w = np.ones_like(p) if weights is None else np.asarray(weights, dtype=np.float64)
    b = np.minimum((p * bins).astype(np.int64), bins - 1)
    wsum = np.bincount(b, w, bins)
    ysum = np.bincount(b, w * y, bins)
    psum = np.bincount(b, w * p, bins)
    ok = wsum > 0
    return float(np.sum(np.abs(ysum[ok] - psum[ok])) / w.sum())


def binary_report(y: np.ndarray, p: np.ndarray, threshold: float = 0.5) -> BinaryReport:
    """Quality of p(glass) ``p`` against labels ``y`` (True = glass)."""
    y = np.asarray(y, dtype=bool)
    p = np.asarray(p, dtype=np.float64)
    pred = p > threshold
    tp = int((pred & y).sum())
    fp = int((pred & ~y).sum())
    fn = int((~pred & y).sum())
    tn = int((~pred & ~y).sum())
    tpr = tp / max(tp + fn, 1)
    tnr = tn / max(tn + fp, 1)
    n_pos, n_neg = max(int(y.sum()), 1), max(int((~y).sum()), 1)
    wb = np.where(y, 0.5 / n_pos, 0.5 / n_neg)
    return BinaryReport(n=int(y.size), n_glass=int(y.sum()), balanced_accuracy=0.5 * (tpr + tnr),
                        precision=tp / max(tp + fp, 1), recall=tpr, roc_auc=roc_auc(y, p),
                        ece=expected_calibration_error(y, p), ece_balanced=expected_calibration_error(y, p, weights=wb))


# -- maps -----------------------------------------------------------------------------------------------------

@dataclass
class MapScore:
    """Classification error of a glass confidence map against the blueprint (fractions in [0, 1]).

    error: share of evaluated wall/glass cells whose map label disagrees with the blueprint (undecided
    or never registered / not occupied counts as an error). glass_recall: share of glass cells labelled
    glass. false_glass_rate: share of wall cells labelled glass. unregistered: share of evaluated cells
    that are not occupied in the map or undecided. error_occupied: the error among evaluated cells that are
    occupied in the map (registration quality without the occupancy grid's misses). n_cells, n_glass,
    n_wall: evaluated cells.
    """

    error: float
    error_occupied: float
    glass_recall: float
    false_glass_rate: float
    unregistered: float
    n_cells: int
    n_glass: int
    n_wall: int


def score_map(map_labels: np.ndarray, truth: np.ndarray, evaluate: np.ndarray) -> MapScore:
    """Score per-cell map labels (1 glass, 0 not glass, -1 undecided, -2 not occupied) against blueprint
    labels ``truth`` (1 wall, 2 glass) on the boolean mask ``evaluate`` (same shape)."""
    if not (map_labels.shape == truth.shape == evaluate.shape):
        raise ValueError(f"shapes differ: map {map_labels.shape}, truth {truth.shape}, mask {evaluate.shape}")
    ev = evaluate & ((truth == 1) | (truth == 2))
    t = truth[ev]
    m = map_labels[ev]
    glass, wall = t == 2, t == 1
    correct = (glass & (m == 1)) | (wall & (m == 0))
    n = int(ev.sum())
    occ = m != -2
    return MapScore(error=float(1.0 - correct.mean()) if n else float("nan"),
                    error_occupied=float(1.0 - correct[occ].mean()) if occ.any() else float("nan"),
                    glass_recall=float((m[glass] == 1).mean()) if glass.any() else float("nan"),
                    false_glass_rate=float((m[wall] == 1).mean()) if wall.any() else float("nan"),
                    unregistered=float((m < 0).mean()) if n else float("nan"),
                    n_cells=n, n_glass=int(glass.sum()), n_wall=int(wall.sum()))
