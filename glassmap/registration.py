"""Registration of per-beam glass probabilities onto grid cells (docs/method.md section 3, eq. 6).

numpy, vectorized over beams, with the per-cell loops compiled (:mod:`glassmap.registration_jit`). Frames: end points are in the map frame (metres);
cells are (ix, iy) of a :class:`~glassmap.grid.MapGrid`, flat index ``iy * width + ix``.

- :func:`nearest_occupied_cells` finds c_hat_j: the occupied cell nearest to each beam end point within a
  small search neighbourhood of the end-point cell (fallback: the end-point cell itself).
- :func:`registration_observations` turns beams into (cell, log-odds) observations for the direct method
  (c_hat_j gets p(g_j)) or the robust method (a k x k window around c_hat_j, eq. 6 decay).
- :func:`aggregate` combines the observations of one scan per cell: ``"scan"`` = the mean log-odds of the
  beams that hit a cell (one observation per cell per scan), ``"beam"`` = the sum (every beam is an
  independent observation, as the paper does).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .registration_jit import (decay_exponents, decayed, nearest_cells, sum_runs, update_windows,
                               window_observations)

Method = Literal["direct", "robust"]
DecayRef = Literal["cell", "endpoint"]
Aggregation = Literal["scan", "beam"]


def logit(p: np.ndarray | float) -> np.ndarray:
    """log(p / (1 - p)); p must lie strictly inside (0, 1)."""
    p = np.asarray(p, dtype=np.float64)
    return np.log(p) - np.log1p(-p)


def decayed_probability(p: np.ndarray, dist: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Eq. 6: ``(p - 0.5) * exp(-dist^2 / (2 sigma^2)) + 0.5``.

    p: classifier output(s); dist: distance(s) in metres; sigma: registration sigma(s) in metres (broadcast).
    sigma = 0 is the limit: weight 1 at distance 0, weight 0 elsewhere.
    """
    p = np.asarray(p, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.exp(-(dist * dist) / (2.0 * sigma * sigma))
    w = np.where(sigma > 0, w, (dist == 0).astype(np.float64))
    return (p - 0.5) * w + 0.5


@functools.lru_cache(maxsize=8)
def window_offsets(k: int) -> np.ndarray:
    """(k*k, 2) integer (dx, dy) offsets of a k x k window centred on (0, 0); k odd. Read-only (cached)."""
    if k < 1 or k % 2 == 0:
        raise ValueError(f"window size k must be a positive odd number (3 or 5), got {k}")
    h = k // 2
    dy, dx = np.mgrid[-h:h + 1, -h:h + 1]
    offs = np.stack([dx.ravel(), dy.ravel()], axis=1).astype(np.int64)
    offs.flags.writeable = False
    return offs


@functools.lru_cache(maxsize=8)
def _window_distances(k: int, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances (m) from the centre cell to the cells of the k x k window: (distinct distances (d,),
    index (k*k,) of each window cell's distance in them, in :func:`window_offsets` order). Read-only."""
    offs = window_offsets(k)
    dist, spread = np.unique(np.hypot(offs[:, 0], offs[:, 1]) * resolution, return_inverse=True)
    dist.flags.writeable = False
    spread.flags.writeable = False
    return dist, spread


def _inside(cells: np.ndarray, shape: tuple[int, int], margin: int) -> np.ndarray:
    h, w = shape
    return ((cells[:, 0] >= margin) & (cells[:, 0] < w - margin) & (cells[:, 1] >= margin)
            & (cells[:, 1] < h - margin))


def nearest_occupied_cells(end_xy: np.ndarray, origin: np.ndarray, resolution: float, occ_log_odds: np.ndarray,
                           occ_threshold_log_odds: float, search_radius: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """c_hat_j for each end point: the occupied cell (log-odds > threshold) whose centre is nearest to the
    end point, among the (2*search_radius+1)^2 cells around the end-point cell; the end-point cell itself
    when none is occupied (or when it lies outside the grid).

    end_xy: (n, 2) map-frame metres. Returns (cells (n, 2) int64 as (ix, iy), found (n,) bool: an occupied
    cell was found). The end-point cell is the nearest cell centre, so an occupied end-point cell is c_hat_j
    directly; only the other beams search their neighbourhood.
    """
    end_xy = np.asarray(end_xy, dtype=np.float64)
    f = (end_xy - origin) / resolution
    offs = window_offsets(2 * max(search_radius, 0) + 1)
    offs = offs[(offs[:, 0] != 0) | (offs[:, 1] != 0)]  # the centre is known to be free/unknown
    h, w = occ_log_odds.shape
    return nearest_cells(f, occ_log_odds.reshape(-1), w, h, occ_log_odds.dtype.type(occ_threshold_log_odds), offs)


@dataclass(frozen=True)
class Observations:
    """Per-(beam, cell) glass evidence of one scan: flat cell indices (m,) and log-odds (m,)."""

    flat: np.ndarray
    log_odds: np.ndarray


@dataclass(frozen=True)
class WindowEvidence:
    """One scan's glass evidence before it is spread over the window cells: window cell q of beam j (cell
    ``centre_cells[j] + offsets[q]``, (ix, iy)) receives the log-odds ``log_odds[j, spread[q]]``; cells outside
    the grid are dropped, and so are log-odds of exactly 0 if ``drop_zero``."""

    centre_cells: np.ndarray
    log_odds: np.ndarray
    spread: np.ndarray
    offsets: np.ndarray
    drop_zero: bool
    returns: np.ndarray | None = None  # (n,) chance that glass returns each beam; None: no visibility scaling


def window_evidence(p_glass: np.ndarray, end_xy: np.ndarray, centre_cells: np.ndarray, sigma: np.ndarray | float,
                    origin: np.ndarray, resolution: float, method: Method = "robust", k: int = 3,
                    decay_ref: DecayRef = "cell", p_clip: float = 1e-3) -> WindowEvidence:
    """The log-odds of the direct or robust registration per beam (see :func:`registration_observations`,
    same arguments), not yet spread over the window cells."""
    p = np.clip(np.asarray(p_glass, dtype=np.float64), p_clip, 1.0 - p_clip)
    n = p.shape[0]
    centre_cells = np.asarray(centre_cells, dtype=np.int64)
    if method == "direct":
        return WindowEvidence(centre_cells, logit(p)[:, None], _CENTRE_SPREAD, window_offsets(1), False)
    if method != "robust":
        raise ValueError(f"registration method must be 'direct' or 'robust', got {method!r}")
    offs = window_offsets(k)
    sg = np.asarray(sigma, dtype=np.float64)
    if sg.shape != (n,):
        sg = np.broadcast_to(sg, (n,))
    sg = np.ascontiguousarray(sg)
    if decay_ref == "cell":
        # the window's cells lie at only a few distinct distances (3 for k = 3): eq. 6 and the logit are
        # evaluated once per beam and distance, then spread over the window
        # (compiled, with numpy's exp and log: the same numbers as decayed_probability and logit)
        dist, spread = _window_distances(k, float(resolution))
        ex = decay_exponents(dist, sg)
        pd = decayed(p, np.exp(ex, out=ex), dist, sg, p_clip, 1.0 - p_clip)
        lo = np.log(pd)
        lo -= np.log1p(np.negative(pd, out=pd), out=pd)
    elif decay_ref == "endpoint":
        centres = origin + (centre_cells[:, None, :] + offs[None, :, :] + 0.5) * resolution
        d = centres - np.asarray(end_xy, dtype=np.float64)[:, None, :]
        dist = np.hypot(d[..., 0], d[..., 1])
        lo = logit(np.clip(decayed_probability(p[:, None], dist, sg[:, None]), p_clip, 1.0 - p_clip))
        spread = _identity_spread(k)
    else:
        raise ValueError(f"decay reference must be 'cell' or 'endpoint', got {decay_ref!r}")
    return WindowEvidence(centre_cells, lo, spread, offs, True)


_CENTRE_SPREAD = np.zeros(1, dtype=np.int64)
_CENTRE_SPREAD.flags.writeable = False


@functools.lru_cache(maxsize=8)
def _identity_spread(k: int) -> np.ndarray:
    spread = np.arange(k * k)
    spread.flags.writeable = False
    return spread


def registration_observations(p_glass: np.ndarray, end_xy: np.ndarray, centre_cells: np.ndarray,
                              sigma: np.ndarray | float, origin: np.ndarray, resolution: float,
                              shape: tuple[int, int], method: Method = "robust", k: int = 3,
                              decay_ref: DecayRef = "cell", p_clip: float = 1e-3) -> Observations:
    """Observations of the direct or robust registration.

    p_glass (n,) classifier outputs in (0, 1); end_xy (n, 2) map-frame end points (m); centre_cells (n, 2)
    c_hat_j as (ix, iy); sigma scalar or (n,) metres. Direct: c_hat_j receives logit(p). Robust: each cell c
    of the k x k window around c_hat_j receives logit of eq. 6, with the distance measured from the centre
    of c_hat_j (``decay_ref="cell"``: c_hat_j gets exactly p) or from the end point (``"endpoint"``).
    Cells outside the grid are dropped; observations of exactly 0.5 (log-odds 0) are dropped (robust only).
    """
    ev = window_evidence(p_glass, end_xy, centre_cells, sigma, origin, resolution, method, k, decay_ref, p_clip)
    h, w = shape
    if method == "direct":
        cells = ev.centre_cells
        ok = _inside(cells, shape, 0)
        return Observations((cells[:, 1] * w + cells[:, 0])[ok], ev.log_odds[ok, 0])
    return Observations(*window_observations(ev.centre_cells, ev.log_odds, ev.spread, ev.offsets, w, h))


def update_with_evidence(layer: np.ndarray, ev: WindowEvidence, aggregation: Aggregation, l_min: float,
                         l_max: float) -> int:
    """Eq. 7 with one scan's evidence, in place on the (H, W) float32 log-odds ``layer``: the numbers of
    :func:`registration_observations`, :func:`aggregate` and :func:`bayes_update` in one compiled pass (no
    observation arrays, no sort). Returns the number of cells updated."""
    if aggregation not in ("scan", "beam"):
        raise ValueError(f"aggregation must be 'scan' or 'beam', got {aggregation!r}")
    if ev.centre_cells.shape[0] == 0:
        return 0
    if not layer.flags.c_contiguous:
        raise ValueError("update_with_evidence needs a C-contiguous layer (it updates it through a flat view)")
    h, w = layer.shape
    if ev.returns is None or ev.offsets.shape[0] == 1:
        returns, centre = _NO_RETURNS, -1
    else:
        returns, centre = np.ascontiguousarray(ev.returns, dtype=np.float64), ev.offsets.shape[0] // 2
    return update_windows(layer.reshape(-1), ev.centre_cells, ev.log_odds, ev.spread, ev.offsets, w, h,
                          ev.drop_zero, aggregation == "scan", float(l_min), float(l_max), returns, centre)


_NO_RETURNS = np.zeros(0)


def aggregate(obs: Observations, aggregation: Aggregation = "scan") -> tuple[np.ndarray, np.ndarray]:
    """Combine one scan's observations per cell. Returns (unique flat cells in increasing order, log-odds
    increment per cell).

    ``"scan"``: the mean log-odds over the observations of the cell (many beams hitting one cell in one
    scan are not independent evidence); ``"beam"``: the sum (every beam counts, the paper's update).
    """
    if aggregation not in ("scan", "beam"):
        raise ValueError(f"aggregation must be 'scan' or 'beam', got {aggregation!r}")
    if obs.flat.size == 0:
        return obs.flat.astype(np.int64), obs.log_odds.astype(np.float64)
    # sort (cell, observation) keys packed in one int64 (a plain sort is several times cheaper than a
    # stable argsort), then add up each cell's observations in observation order
    lo_idx, hi_idx = int(obs.flat.min()), int(obs.flat.max())
    m = obs.flat.size
    shift = max(m.bit_length(), 1)
    if hi_idx - lo_idx < 1 << (62 - shift):
        key = obs.flat - lo_idx
        key <<= shift
        key |= np.arange(m)
        key.sort()
        order = key & ((1 << shift) - 1)
        key >>= shift
        key += lo_idx
    else:
        order = np.argsort(obs.flat, kind="stable")
        key = obs.flat[order]
    uniq, total, count = sum_runs(key, order, obs.log_odds.astype(np.float64, copy=False))
    if aggregation == "beam":
        return uniq, total
    return uniq, total / count


def bayes_update(layer: np.ndarray, flat: np.ndarray, delta: np.ndarray, l_min: float, l_max: float) -> None:
    """Eq. 7 in log-odds on the cells ``flat`` of ``layer`` (in place): l += delta, clamped to
    [l_min, l_max]. ``flat`` must be unique (use :func:`aggregate`)."""
    v = layer.reshape(-1)
    v[flat] = np.clip(v[flat] + delta, l_min, l_max)
