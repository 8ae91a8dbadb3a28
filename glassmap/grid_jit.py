"""Compiled occupancy update of one scan (:meth:`glassmap.grid.OccupancyGrid.integrate`), numba ``njit``.

The same float32 operations in the same order as the numpy ray walk it replaced (no fast-math), so the
log-odds are the same to the last bit. Cells are flat indices ``iy * w + ix`` of a grid of ``h`` rows and
``w`` columns. Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from .jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


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
