"""Compiled occupancy update of one scan (:meth:`glassmap.grid.OccupancyGrid.integrate`) and the per-beam
passes of the mapper (:class:`glassmap.mapping.GlassMapper`: its beam masks and glass hits), numba ``njit``.

The same operations in the same order and precision as the numpy code they replaced (no fast-math), so the
log-odds are the same to the last bit. Cells are flat indices ``iy * w + ix`` of a grid of ``h`` rows and
``w`` columns. Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def scan_reach(c: np.ndarray, s: np.ndarray, ranges: np.ndarray, px: float, py: float, range_max: float,
               max_free_range: float, no_return_range: float):
    """What one scan reaches in the map frame. c, s (n,): the beams' map-frame direction cosines and sines;
    ranges (n,) m; (px, py): the laser position (m).

    Returns hit (n,) bool: a return within ``range_max`` (finite); clear (n,) bool: the beam clears space
    (a hit, or no return (+inf) when ``no_return_range`` > 0); free_len (n,) m: how far it clears (its range
    clipped to [0, ``max_free_range``] for a hit, else ``no_return_range``); ends (2, n) m: end points (x row,
    y row; the laser position for beams without a hit); the number of clearing beams; and the box (4,) m
    (x min, y min, x max, y max) around the hits' end points, the clearing beams' reach and the laser
    (NaN if a coordinate is NaN)."""
    n = ranges.shape[0]
    hit = np.empty(n, np.bool_)
    clear = np.empty(n, np.bool_)
    free_len = np.empty(n)
    ends = np.empty((2, n))
    box = np.array([px, py, px, py])
    n_clear = 0
    for b in range(n):
        r = ranges[b]
        h = math.isfinite(r) and r <= range_max
        hit[b] = h
        rr = r if h else 0.0
        x = c[b] * rr + px
        y = s[b] * rr + py
        ends[0, b], ends[1, b] = x, y
        clear[b] = h or (r == np.inf and no_return_range > 0)
        free_len[b] = min(max(r, 0.0), max_free_range) if h else no_return_range
        if h:
            _extend(box, x, y)
        if clear[b]:
            n_clear += 1
            _extend(box, px + c[b] * free_len[b], py + s[b] * free_len[b])
    return hit, clear, free_len, ends, n_clear, box


@_jit
def _extend(box: np.ndarray, x: float, y: float) -> None:
    """Grow the box (x min, y min, x max, y max) to hold (x, y); a NaN coordinate stays in it (as np.min)."""
    if box[0] == box[0] and not x >= box[0]:
        box[0] = x
    if box[1] == box[1] and not y >= box[1]:
        box[1] = y
    if box[2] == box[2] and not x <= box[2]:
        box[2] = x
    if box[3] == box[3] and not y <= box[3]:
        box[3] = y


@_jit
def bounds(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The box (4,) (x min, y min, x max, y max) of the n >= 1 points (x, y) (NaN if a coordinate is NaN, as
    np.min / np.max)."""
    box = np.array([x[0], y[0], x[0], y[0]])
    for j in range(1, x.shape[0]):
        _extend(box, x[j], y[j])
    return box


@_jit
def hit_margins(c: np.ndarray, s: np.ndarray, ranges: np.ndarray, hit: np.ndarray, edge: float, surface: float,
                k: int, chord: float) -> np.ndarray:
    """Per beam, how far short of its end point it stops clearing (m): ``surface`` for a beam whose
    neighbours ``k`` beams either side both have hits less than ``chord`` (m) apart, ``edge`` otherwise.
    c, s (n,): the beams' direction cosines and sines (any one frame); ranges (n,) m; hit (n,) bool."""
    n = ranges.shape[0]
    margins = np.full(n, edge)
    if n > 2 * k and surface != edge:
        for b in range(k, n - k):
            i, j = b - k, b + k
            if hit[i] and hit[j]:
                if math.hypot(ranges[j] * c[j] - ranges[i] * c[i], ranges[j] * s[j] - ranges[i] * s[i]) < chord:
                    margins[b] = surface
    return margins


@_jit
def beam_walks(c: np.ndarray, s: np.ndarray, ranges: np.ndarray, hit: np.ndarray, clear: np.ndarray,
               free_len: np.ndarray, ends: np.ndarray, ox: float, oy: float, resolution: float, w: int,
               step: float, edge: float, surface: float, k: int, chord: float):
    """The arguments of :func:`free_and_hit_update` for one scan (the outputs of :func:`scan_reach`, the grid's
    origin (ox, oy) m, resolution m and width ``w`` cells): per clearing beam its direction over the
    resolution (dx, dy float32) and its number of samples ``step`` (m) apart up to :func:`hit_margins` short
    of a hit; and the flat cells of the hits' end points."""
    margins = hit_margins(c, s, ranges, hit, edge, surface, k, chord)
    n = ranges.shape[0]
    m = 0
    n_hit = 0
    for b in range(n):
        m += clear[b]
        n_hit += hit[b]
    dx = np.empty(m, np.float32)
    dy = np.empty(m, np.float32)
    counts = np.empty(m, np.int64)
    cells = np.empty(n_hit, np.int64)
    m = 0
    n_hit = 0
    for b in range(n):
        if clear[b]:
            length = free_len[b] - (margins[b] if hit[b] else 0.0)
            counts[m] = math.ceil(max(length, 0.0) / step)
            dx[m] = np.float32(c[b] / resolution)
            dy[m] = np.float32(s[b] / resolution)
            m += 1
        if hit[b]:
            ix = np.int64(math.floor((ends[0, b] - ox) / resolution))
            iy = np.int64(math.floor((ends[1, b] - oy) / resolution))
            cells[n_hit] = iy * w + ix
            n_hit += 1
    return dx, dy, counts, cells


@_jit
def free_and_hit_update(lo: np.ndarray, protect: np.ndarray, seen: np.ndarray, w: int, fx: np.float32,
                        fy: np.float32, dx: np.ndarray, dy: np.ndarray, counts: np.ndarray, step: np.float32,
                        l_free: np.float32, hit_cells: np.ndarray, l_occ: np.float32, l_min: np.float32,
                        l_max: np.float32) -> None:
    """Add ``l_free`` once to every cell the clearing beams cross and then ``l_occ`` once to every cell in
    ``hit_cells``, in place on the flat float32 log-odds ``lo``; then clamp the cells changed to
    [``l_min``, ``l_max``] (the other cells are within them already: every update clamps what it changed).

    Beam b is sampled at t = i * step cells, i = 0 .. counts[b] - 1, from the laser at (fx, fy) (cells from
    the grid's corner) along (dx[b], dy[b]) (its direction over the resolution); a sample lies in cell
    (floor(fx + dx t), floor(fy + dy t)). Cells marked in the flat bool ``protect`` (size 0: none) are not
    lowered. Samples off the grid are skipped (the caller grew the grid to hold the scan). ``seen``: flat
    uint8 scratch of the grid's size, all 0 (and all 0 again on return), so that the cost follows the
    scan, not the size of the map."""
    size = lo.shape[0]
    touched = np.empty(counts.sum() + hit_cells.shape[0], np.int64)  # cells changed (at most one per sample)
    longest = 0
    for b in range(counts.shape[0]):
        longest = max(longest, counts[b])
    cells = np.empty(longest, np.int64)  # one beam's sample cells, then its runs of one cell
    n = 0
    guard = protect.shape[0] > 0
    # Branch-free passes per beam: mispredicted branches (is this sample in the cell of the one before? was
    # this cell lowered already?) cost more than the arithmetic.
    for b in range(counts.shape[0]):
        cx, cy = dx[b], dy[b]
        m = counts[b]
        for i in range(m):  # the sample cells (vectorised by LLVM)
            t = np.float32(i) * step
            cells[i] = np.int64(np.floor(fy + cy * t)) * w + np.int64(np.floor(fx + cx * t))
        k = 0
        last = -1
        for i in range(m):  # most samples fall in the cell of the one before: keep one per run
            cell = cells[i]
            cells[k] = cell
            k += cell != last
            last = cell
        for j in range(k):  # lower each cell once: off-grid, protected or lowered cells leave lo as it is
            cell = cells[j]
            on_grid = (cell >= 0) & (cell < size)
            c = cell if on_grid else 0
            fresh = on_grid & (seen[c] == 0)
            if guard:
                fresh = fresh & (not protect[c])
            touched[n] = c
            n += fresh
            seen[c] = seen[c] | np.uint8(fresh)  # 1: lowered this scan, 2: raised this scan
            v = lo[c]
            lo[c] = v + l_free if fresh else v
    for j in range(hit_cells.shape[0]):
        cell = hit_cells[j]
        if cell < 0 or cell >= size or seen[cell] == 2:
            continue
        if seen[cell] == 0:
            touched[n] = cell
            n += 1
        seen[cell] = 2
        lo[cell] = lo[cell] + l_occ
    for k in range(n):  # as np.clip (NaN stays NaN)
        cell = touched[k]
        v = lo[cell]
        if v < l_min:
            lo[cell] = l_min
        elif v > l_max:
            lo[cell] = l_max
        seen[cell] = 0


@_jit
def raise_end_cells(lo: np.ndarray, marks: np.ndarray, x: np.ndarray, y: np.ndarray, ox: float, oy: float,
                    resolution: float, w: int, floor_value: np.float32, occupy: bool) -> None:
    """For each map-frame point (x[j], y[j]) (m): its cell (floor((x - ox) / resolution), likewise y), then
    (``occupy``) the flat float32 log-odds ``lo`` of the cell raised to at least ``floor_value`` and (if
    ``marks`` is not empty) the flat bool ``marks`` of the cell set. The caller grew the grid to hold the
    points."""
    mark = marks.shape[0] > 0
    for j in range(x.shape[0]):
        c = np.int64(np.floor((y[j] - oy) / resolution)) * w + np.int64(np.floor((x[j] - ox) / resolution))
        if occupy and not lo[c] >= floor_value:
            lo[c] = floor_value
        if mark:
            marks[c] = True


@_jit
def ranged_beams(r: np.ndarray, range_min: float, range_max: float) -> tuple[np.ndarray, int, int]:
    """The ranges r (n,) m with NaN where a beam has no usable range (not finite, or outside [range_min,
    range_max]); the number of usable ranges and the number of NaN ranges."""
    n = r.shape[0]
    out = np.empty(n)
    n_ranged = 0
    n_nan = 0
    for b in range(n):
        v = r[b]
        if math.isfinite(v) and v >= range_min and v <= range_max:
            out[b] = v
            n_ranged += 1
        else:
            out[b] = np.nan
            n_nan += v != v
    return out, n_ranged, n_nan


@_jit
def classified_beams(incidence: np.ndarray, intensities: np.ndarray,
                     r: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """The beams the classifier sees, (n,) bool: a finite incidence angle (rad) and a finite intensity; the
    numbers of beams with an angle, of beams whose range r (m) is not NaN but whose intensity is not finite,
    and of beams seen."""
    n = r.shape[0]
    use = np.empty(n, np.bool_)
    n_angle = 0
    n_bad = 0
    n_use = 0
    for b in range(n):
        angle = math.isfinite(incidence[b])
        finite_i = math.isfinite(intensities[b])
        use[b] = angle and finite_i
        n_angle += angle
        n_bad += not finite_i and r[b] == r[b]
        n_use += use[b]
    return use, n_angle, n_bad, n_use
