"""Images of the glass confidence map in the paper's colours (numpy rendering, PNG via matplotlib.image).

Free cells white, unknown cells green, occupied cells on a blue (p(glass) 0, certainly not glass) -> gray
(0.5, uncertain) -> red (1, certainly glass) scale. Image row 0 is the top of the map (highest y).
"""

from __future__ import annotations

import numpy as np

WHITE = np.array([1.0, 1.0, 1.0])
GREEN = np.array([0.55, 0.80, 0.45])
BLUE = np.array([0.0, 0.15, 1.0])
GRAY = np.array([0.55, 0.55, 0.55])
RED = np.array([1.0, 0.0, 0.0])


def confidence_colours(p: np.ndarray) -> np.ndarray:
    """RGB (..., 3) in [0, 1] for p(glass) values: blue at 0, gray at 0.5, red at 1."""
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)[..., None]
    lo = BLUE + (GRAY - BLUE) * (p / 0.5)
    hi = GRAY + (RED - GRAY) * ((p - 0.5) / 0.5)
    return np.where(p < 0.5, lo, hi)


def glass_confidence_rgb(confidence: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 image, rows flipped so that row 0 = highest y.

    confidence: (H, W) p(glass) on occupied cells, NaN elsewhere; free: (H, W) bool free cells.
    Cells that are neither occupied nor free are unknown (green).
    """
    confidence = np.asarray(confidence)
    free = np.asarray(free, dtype=bool)
    if confidence.shape != free.shape or confidence.ndim != 2:
        raise ValueError(f"confidence {confidence.shape} and free {free.shape} must be equal 2-D shapes")
    rgb = np.empty(confidence.shape + (3,))
    rgb[:] = GREEN
    rgb[free] = WHITE
    occ = np.isfinite(confidence)
    rgb[occ] = confidence_colours(confidence[occ])
    return (rgb[::-1] * 255 + 0.5).astype(np.uint8)


def glass_confidence_png(path: str, confidence: np.ndarray, free: np.ndarray, scale: int = 1,
                         crop: bool = True, margin: int = 10) -> str:
    """Write the glass confidence map as PNG (paper colours). ``scale`` repeats each cell scale x scale
    pixels; ``crop`` trims to the explored area (non-unknown cells) plus ``margin`` cells. Returns path."""
    import matplotlib.image as mpimg

    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    confidence = np.asarray(confidence)
    free = np.asarray(free, dtype=bool)
    if crop:
        known = free | np.isfinite(confidence)
        if known.any():
            rows, cols = np.nonzero(known)
            r0, r1 = max(rows.min() - margin, 0), min(rows.max() + margin + 1, known.shape[0])
            c0, c1 = max(cols.min() - margin, 0), min(cols.max() + margin + 1, known.shape[1])
            confidence, free = confidence[r0:r1, c0:c1], free[r0:r1, c0:c1]
    img = glass_confidence_rgb(confidence, free)
    if scale > 1:
        img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    mpimg.imsave(path, img)
    return path
