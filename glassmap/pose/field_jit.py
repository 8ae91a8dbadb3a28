"""Compiled passes of the likelihood field (:mod:`glassmap.pose.field`), numba ``njit``.

A maximum is exact, so the result equals scipy's to the last bit whatever the order of the comparisons (the
field holds no NaN); the nearest occupied cells are those of scipy's exact distance transform, ties included
(:func:`near_cells`); the other passes do the integer arithmetic and the floating-point operations of the
numpy code they replaced, in the same order (no fast-math), so their results are the same to the last bit.
Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from glassmap.jit import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def forward_maximum(a: np.ndarray, f: int) -> np.ndarray:
    """out[y, x] = max of a[y .. y + f - 1, x .. x + f - 1], indices past the last row / column clamped to
    it: ``scipy.ndimage.maximum_filter(a, size=f, origin=-(f // 2), mode="nearest")`` for a 2-D array
    without NaN."""
    h, w = a.shape
    rows = a.copy()  # the maximum over x .. x + f - 1 of each row
    for y in range(h):
        ry, ay = rows[y], a[y]
        for d in range(1, f):
            for x in range(max(w - d, 0)):  # contiguous: vectorised
                if ay[x + d] > ry[x]:
                    ry[x] = ay[x + d]
            for x in range(max(w - d, 0), w):  # past the last column: the last column
                if ay[w - 1] > ry[x]:
                    ry[x] = ay[w - 1]
    out = rows.copy()
    for y in range(h):
        oy = out[y]
        for d in range(1, f):
            r = rows[min(y + d, h - 1)]
            for x in range(w):
                if r[x] > oy[x]:
                    oy[x] = r[x]
    return out


@_jit
def near_cells(occ: np.ndarray, cut2: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                    np.ndarray]:
    """The cells (row-major order, as ``np.nonzero``) of the (H, W) bool grid ``occ`` whose nearest occupied
    cell lies within sqrt(``cut2``) cells: their rows and columns (int64), the nearest cell's row and column
    and the offset to it (ddy, ddx) (int32). Of equally near occupied cells the one of the lowest column,
    then the lowest row, is taken: the cell ``scipy.ndimage.distance_transform_edt(~occ,
    return_indices=True)`` gives. Each occupied cell visits only the cells within the cut."""
    h, w = occ.shape
    r = 0
    while (r + 1) * (r + 1) <= cut2:
        r += 1
    big = np.int32(cut2 + 1)
    best = np.full((h, w), big, np.int32)  # squared distance to the nearest occupied cell so far
    near = np.empty((h, w), np.int32)  # its flat index
    flat = occ.ravel()
    for f in range(h * w):
        if not flat[f]:
            continue
        oy, ox = f // w, f % w
        for dy in range(max(-r, -oy), min(r, h - 1 - oy) + 1):
            y = oy + dy
            for dx in range(max(-r, -ox), min(r, w - 1 - ox) + 1):
                d2 = np.int32(dy * dy + dx * dx)
                if d2 > cut2:
                    continue
                x = ox + dx
                b = best[y, x]
                if d2 < b:
                    best[y, x] = d2
                    near[y, x] = f
                elif d2 == b:
                    g = near[y, x]
                    if ox < g % w or (ox == g % w and f < g):  # lower column, then lower row
                        near[y, x] = f
    bf, nf = best.ravel(), near.ravel()
    n = 0
    for f in range(h * w):
        n += bf[f] < big
    iy, ix = np.empty(n, np.int64), np.empty(n, np.int64)
    ny, nx = np.empty(n, np.int32), np.empty(n, np.int32)
    k = 0
    for f in range(h * w):
        if bf[f] < big:
            iy[k], ix[k], ny[k], nx[k] = f // w, f % w, nf[f] // w, nf[f] % w
            k += 1
    return iy, ix, ny, nx, ny - iy.astype(np.int32), nx - ix.astype(np.int32)


@_jit
def unique_cells(oy: np.ndarray, ox: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(oy * w + ox, return_inverse=True)`` for cells (oy, ox) of an (h, w) grid: the distinct
    flat indices in increasing order, and for each input the position of its own among them."""
    slot = np.full(h * w, -1, np.int32)
    for k in range(oy.shape[0]):
        slot[np.int64(oy[k]) * w + ox[k]] = 0
    n = 0
    for f in range(h * w):
        if slot[f] == 0:
            slot[f] = n
            n += 1
    u = np.empty(n, np.int64)
    inv = np.empty(oy.shape[0], np.int64)
    for k in range(oy.shape[0]):
        f = np.int64(oy[k]) * w + ox[k]
        u[slot[f]] = f
        inv[k] = slot[f]
    return u, inv


@_jit
def neighbour_sums(sx: np.ndarray, sy: np.ndarray, cnt: np.ndarray, cy: np.ndarray, cx: np.ndarray, r: int,
                   res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each requested cell (cy[u], cx[u]) and each of the (2 r + 1)^2 neighbours (dy, dx) (row-major,
    dy and dx from -r to r): the neighbour's count c and its sums of x and y offsets moved to the requested
    cell's corner, sx + c * dx * res and sy + c * dy * res (m), 0 off the grid; (U, (2 r + 1)^2) float64
    each. ``sx``, ``sy``, ``cnt``: (H, W) float32 end-point layers."""
    h, w = cnt.shape
    m = 2 * r + 1
    c = np.empty((cy.shape[0], m * m))
    ax = np.empty((cy.shape[0], m * m))
    ay = np.empty((cy.shape[0], m * m))
    for u in range(cy.shape[0]):
        for j in range(m * m):
            dy = j // m - r
            dx = j % m - r
            y = cy[u] + dy
            x = cx[u] + dx
            inside = 0 <= y < h and 0 <= x < w
            cv = np.float64(cnt[y, x]) if inside else 0.0
            c[u, j] = cv
            ax[u, j] = (np.float64(sx[y, x]) if inside else 0.0) + cv * (np.float64(dx) * res)
            ay[u, j] = (np.float64(sy[y, x]) if inside else 0.0) + cv * (np.float64(dy) * res)
    return c, ax, ay


@_jit
def changed_cells(occ: np.ndarray, occ_old: np.ndarray, cnt: np.ndarray, cnt_old: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows and columns (int64) of the cells where the (H, W) bool ``occ`` differs from ``occ_old``, then of
    those where ``cnt`` differs from ``cnt_old``; ``cnt_old`` is set to ``cnt`` on the way (in place)."""
    h, w = occ.shape
    fy, fx = np.empty(h * w, np.int64), np.empty(h * w, np.int64)
    cy, cx = np.empty(h * w, np.int64), np.empty(h * w, np.int64)
    nf = nc = 0
    for y in range(h):
        for x in range(w):
            if occ[y, x] != occ_old[y, x]:
                fy[nf], fx[nf] = y, x
                nf += 1
            if cnt[y, x] != cnt_old[y, x]:
                cnt_old[y, x] = cnt[y, x]
                cy[nc], cx[nc] = y, x
                nc += 1
    return fy[:nf], fx[:nf], cy[:nc], cx[:nc]


@_jit
def _window_cells(cy: np.ndarray, cx: np.ndarray, r: int, mark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells within ``r`` cells (Chebyshev) of any of the cells (cy, cx) of the grid of ``mark`` (each once,
    in the order first reached): rows and columns (int64). ``mark``: (H, W) bool scratch, all False on entry
    and on return."""
    h, w = mark.shape
    n = 0
    for k in range(cy.shape[0]):
        for y in range(max(cy[k] - r, 0), min(cy[k] + r, h - 1) + 1):
            for x in range(max(cx[k] - r, 0), min(cx[k] + r, w - 1) + 1):
                if not mark[y, x]:
                    mark[y, x] = True
                    n += 1
    ys, xs = np.empty(n, np.int64), np.empty(n, np.int64)
    j = 0
    for k in range(cy.shape[0]):
        for y in range(max(cy[k] - r, 0), min(cy[k] + r, h - 1) + 1):
            for x in range(max(cx[k] - r, 0), min(cx[k] + r, w - 1) + 1):
                if mark[y, x]:
                    mark[y, x] = False
                    ys[j], xs[j] = y, x
                    j += 1
    return ys, xs


@_jit
def renew_nearest(occ: np.ndarray, nearest: np.ndarray, cy: np.ndarray, cx: np.ndarray, cut2: int,
                  mark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """After the occupied cells (H, W) ``occ`` changed at the cells (cy, cx): recompute ``nearest`` (H, W)
    int32, the flat index of each cell's nearest occupied cell within sqrt(``cut2``) cells (-1: none; ties
    as :func:`near_cells`), at every cell that can have changed (within the cut of a changed cell), in
    place. Returns those cells' rows and columns. ``mark``: as :func:`_window_cells`."""
    h, w = occ.shape
    r = 0
    while (r + 1) * (r + 1) <= cut2:
        r += 1
    ys, xs = _window_cells(cy, cx, r, mark)
    for k in range(ys.shape[0]):
        y, x = ys[k], xs[k]
        bd, bf = cut2 + 1, -1
        for oy in range(max(y - r, 0), min(y + r, h - 1) + 1):
            for ox in range(max(x - r, 0), min(x + r, w - 1) + 1):
                if not occ[oy, ox]:
                    continue
                d2 = (oy - y) * (oy - y) + (ox - x) * (ox - x)
                if d2 > cut2:
                    continue
                f = oy * w + ox
                if d2 < bd or (d2 == bd and (ox < bf % w or (ox == bf % w and f < bf))):
                    bd, bf = d2, f
        nearest[y, x] = bf
    return ys, xs


@_jit
def cells_of_walls(nearest: np.ndarray, cy: np.ndarray, cx: np.ndarray, k: int, r: int, skip: np.ndarray,
                   mark: np.ndarray, wall: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells whose nearest occupied cell (``nearest``, as :func:`renew_nearest`; it lies within ``r``
    cells) lies within ``k`` cells (Chebyshev) of one of the cells (cy, cx), but not the cells (flat indices)
    ``skip``: rows and columns (int64). ``mark``, ``wall``: (H, W) bool scratch, all False on entry and on
    return."""
    h, w = nearest.shape
    wy, wx = _window_cells(cy, cx, k, wall)
    for j in range(wy.shape[0]):
        wall[wy[j], wx[j]] = True
    ys, xs = _window_cells(cy, cx, k + r, mark)
    flat = mark.ravel()
    for j in range(skip.shape[0]):
        flat[skip[j]] = True
    keep = np.zeros(ys.shape[0], np.bool_)
    for j in range(ys.shape[0]):
        f = nearest[ys[j], xs[j]]
        keep[j] = f >= 0 and not mark[ys[j], xs[j]] and wall[f // w, f % w]
    for j in range(skip.shape[0]):
        flat[skip[j]] = False
    for j in range(wy.shape[0]):
        wall[wy[j], wx[j]] = False
    return ys[keep], xs[keep]


@_jit
def forward_maximum_at(a: np.ndarray, out: np.ndarray, cy: np.ndarray, cx: np.ndarray, f: int,
                       mark: np.ndarray) -> None:
    """After ``a`` changed at the cells (cy, cx): recompute ``out = forward_maximum(a, f)`` in place at the
    cells whose f x f block holds one of them. ``mark``: as :func:`_window_cells`."""
    h, w = a.shape
    for k in range(cy.shape[0]):
        for y in range(max(cy[k] - f + 1, 0), cy[k] + 1):
            for x in range(max(cx[k] - f + 1, 0), cx[k] + 1):
                if mark[y, x]:
                    continue
                mark[y, x] = True
                m = a[y, x]
                for dy in range(f):
                    ry = a[min(y + dy, h - 1)]
                    for dx in range(f):
                        v = ry[min(x + dx, w - 1)]
                        if v > m:
                            m = v
                out[y, x] = m
    for k in range(cy.shape[0]):
        for y in range(max(cy[k] - f + 1, 0), cy[k] + 1):
            for x in range(max(cx[k] - f + 1, 0), cx[k] + 1):
                mark[y, x] = False


@_jit
def wall_vectors(vx: np.ndarray, vy: np.ndarray, xy: np.ndarray, ox: float, oy: float, res: float, w: int,
                 h: int) -> np.ndarray:
    """Per map-frame point of ``xy`` (n, 2) (m): the vector (m) of the flat (h, w) float32 arrays ``vx``, ``vy``
    (corner (ox, oy) m, cells ``res`` m) interpolated bilinearly between the four cell centres around it,
    in float64 (corners in the order (0, 0), (1, 0), (0, 1), (1, 1), summed from 0); NaN where those are
    not all inside."""
    n = xy.shape[0]
    out = np.full((n, 2), np.nan)
    for i in range(n):
        gx = (xy[i, 0] - ox) / res - 0.5  # cell centres at integer coordinates
        gy = (xy[i, 1] - oy) / res - 0.5
        x0, y0 = np.floor(gx), np.floor(gy)
        if not (x0 >= 0 and y0 >= 0 and x0 < w - 1 and y0 < h - 1):
            continue
        ax, ay = gx - x0, gy - y0
        c00, c10, c01, c11 = (1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay
        b = np.int64(y0 * w + x0)
        out[i, 0] = 0.0 + c00 * np.float64(vx[b]) + c10 * np.float64(vx[b + 1]) + c01 * np.float64(vx[b + w]) \
            + c11 * np.float64(vx[b + w + 1])
        out[i, 1] = 0.0 + c00 * np.float64(vy[b]) + c10 * np.float64(vy[b + 1]) + c01 * np.float64(vy[b + w]) \
            + c11 * np.float64(vy[b + w + 1])
    return out


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) the kernels now, with the argument types the field
    passes, rather than at the first rebuild."""
    forward_maximum(np.zeros((1, 1), np.float32), 1)
    near_cells(np.zeros((1, 1), np.bool_), 1)
    unique_cells(np.zeros(1, np.int32), np.zeros(1, np.int32), 1, 1)
    layer = np.zeros((1, 1), np.float32)
    neighbour_sums(layer, layer, layer, np.zeros(1, np.int64), np.zeros(1, np.int64), 1, 0.05)
    one, flag = np.zeros(1, np.int64), np.zeros((1, 1), np.bool_)
    changed_cells(flag, flag, layer, layer.copy())
    changed_cells(flag, flag, flag, flag.copy())
    nearest = np.full((1, 1), -1, np.int32)
    renew_nearest(flag, nearest, one, one, 1, flag.copy())
    cells_of_walls(nearest, one, one, 2, 1, one, flag.copy(), flag.copy())
    forward_maximum_at(layer, layer.copy(), one, one, 1, flag.copy())
    flat = np.zeros(4, np.float32)
    wall_vectors(flat, flat, np.zeros((1, 2)), 0.0, 0.0, 1.0, 2, 2)
