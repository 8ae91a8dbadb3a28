"""Compiled decoding of SCIP multi-echo scan data (ND, NE, HD, HE), numba ``njit``: the fast path of
:func:`drivers.hokuyo.scip.decode_scan_data`.

It decodes well-formed data only and says so; on anything else (a stray ``&``, a character outside the
6-bit alphabet, too many echoes, a partial echo) the caller decodes with the numpy code, which raises the
precise error. For well-formed data the values are the numpy code's. Compiled code is cached on disk.
"""

from __future__ import annotations

import numba
import numpy as np

AMP = 0x26  # '&': the next echo belongs to the same step


@numba.njit(cache=True, nogil=True)
def decode_multi(a: np.ndarray, width: int, nval: int,
                 max_echoes: int) -> tuple[bool, np.ndarray, np.ndarray]:
    """Multi-echo data ``a`` (uint8, lines joined, checksums removed) of ``nval`` values of ``width``
    characters per echo. Returns (ok, values (steps, max_echoes) int32, intensities (steps, max_echoes)
    int32; -1 where a step has fewer echoes; intensities all -1 when nval is 1); ok is False (and the
    arrays empty) unless the data are well formed."""
    rec = width * nval
    bad = np.full((0, max_echoes), -1, np.int32)
    n_amp = 0
    pos = 0  # position of the next data character inside its echo
    for i in range(a.size):
        if a[i] == AMP:  # must sit between two echoes, before an echo
            if i == 0 or pos != 0 or i + 1 >= a.size or a[i + 1] == AMP:
                return False, bad, bad
            n_amp += 1
        else:
            if a[i] - 0x30 > 0x3F or a[i] < 0x30:
                return False, bad, bad
            pos += 1
            if pos == rec:  # (pos + 1) % rec without the division
                pos = 0
    nchars = a.size - n_amp
    if pos != 0 or nchars == 0:
        return False, bad, bad
    steps = nchars // rec - n_amp
    val = np.full((steps, max_echoes), -1, np.int32)
    inten = np.full((steps, max_echoes), -1, np.int32)
    step = -1
    echo = 0
    i = 0
    while i < a.size:
        if a[i] == AMP:
            echo += 1
            if echo >= max_echoes:
                return False, bad, bad
            i += 1
        else:
            step += 1
            echo = 0
        for v in range(nval):
            x = 0
            for c in range(width):
                x = (x << 6) | (np.int64(a[i]) - 0x30)
                i += 1
            if v == 0:
                val[step, echo] = x
            else:
                inten[step, echo] = x
    return True, val, inten


@numba.njit(cache=True, nogil=True)
def metres(mm: np.ndarray, dmin: int, dmax: int) -> np.ndarray:
    """Millimetres (steps, k) int64 -> metres (steps, k) float64, as :func:`drivers.hokuyo.scip.distances_to_metres`:
    +inf for code 1 and above ``dmax``, NaN for the other values below ``dmin``."""
    out = np.empty(mm.shape, np.float64)
    for i in range(mm.shape[0]):
        for j in range(mm.shape[1]):
            v = mm[i, j]
            if v == 1 or v > dmax:
                out[i, j] = np.inf
            elif v < dmin:
                out[i, j] = np.nan
            else:
                out[i, j] = np.float64(v) * 1e-3
    return out


@numba.njit(cache=True, nogil=True)
def echo_metres(multi: np.ndarray, dmin: int, dmax: int) -> np.ndarray:
    """Echoes after the first of multi-echo millimetres (steps, k) integer -> metres (steps, k - 1) float64,
    as :func:`metres` (no strided copy of the columns first)."""
    n, k = multi.shape
    out = np.empty((n, max(k - 1, 0)), np.float64)
    for i in range(n):
        for j in range(1, k):
            v = multi[i, j]
            if v == 1 or v > dmax:
                out[i, j - 1] = np.inf
            elif v < dmin:
                out[i, j - 1] = np.nan
            else:
                out[i, j - 1] = np.float64(v) * 1e-3
    return out


@numba.njit(cache=True, nogil=True)
def echo_intensities(multi: np.ndarray, inten: np.ndarray) -> np.ndarray:
    """Intensities (steps, k) of the echoes after the first -> float64 (steps, k - 1), NaN where the echo is
    absent (``multi`` < 0)."""
    n, k = multi.shape
    out = np.empty((n, max(k - 1, 0)), np.float64)
    for i in range(n):
        for j in range(1, k):
            out[i, j - 1] = np.float64(inten[i, j]) if multi[i, j] >= 0 else np.nan
    return out


@numba.njit(cache=True, nogil=True)
def scan_frames(buf: np.ndarray, verify: bool, line_payload: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The whole scan-shaped messages at the head of ``buf`` (uint8): an echo line, a status line, a 4-character
    timestamp line, data lines of ``line_payload`` characters and a last one of at least one, each with its
    checksum character, then a blank line. Returns (frames (m, 4) int64: each message's first byte and the LFs
    ending its echo line, its status line and the message; data (uint8): the messages' data characters
    joined, checksums removed; offsets (m + 1,) of each message's data in it). Stops at the first message
    framed otherwise or, with ``verify``, with a bad checksum on a timestamp or data line (the echo and
    status lines are the caller's to check)."""
    lf = np.flatnonzero(buf == 0x0A)
    frames = np.empty((lf.size // 4, 4), np.int64)
    data = np.empty(buf.size, np.uint8)
    offsets = np.zeros(lf.size // 4 + 1, np.int64)
    m = 0
    done = 0  # first byte of the next message
    li = 0  # index into lf of the next message's first line end
    for bi in range(lf.size - 1):
        if lf[bi + 1] - lf[bi] != 1:
            continue
        if bi + 1 - li < 4 or lf[li] <= done:  # fewer than 4 lines before the blank line, or an empty echo line
            break
        i2 = lf[li + 1]
        ok = True
        start = i2 + 1  # first byte of the line
        n_out = offsets[m]
        for k in range(li + 2, bi + 1):
            end = lf[k]  # the line's LF
            n = end - start  # characters, checksum included
            first, last = k == li + 2, k == bi
            bad = (n != 5) if first else ((n < 2) if last else (n != line_payload + 1))
            if bad:
                ok = False
                break
            if verify:
                s = 0
                for j in range(start, end - 1):
                    s += buf[j]
                if (s & 0x3F) + 0x30 != buf[end - 1]:
                    ok = False
                    break
            if not first:
                data[n_out:n_out + n - 1] = buf[start:end - 1]
                n_out += n - 1
            start = end + 1
        if not ok:
            break
        frames[m, 0], frames[m, 1], frames[m, 2], frames[m, 3] = done, lf[li], i2, lf[bi + 1]
        m += 1
        offsets[m] = n_out
        done = lf[bi + 1] + 1
        li = bi + 2
    return frames[:m], data[:offsets[m]], offsets[:m + 1]
