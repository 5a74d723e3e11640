"""Cropping and resampling of point sets: the one implementation behind the env's observations
and the supervised training samples (so that what a tracker is trained on is what it sees).
"""

from __future__ import annotations

import numpy as np

TEMPLATE_SIZE = 512
SEARCH_SIZE = 1024
TEMPLATE_SCALE = 1.25
SEARCH_SCALE = 1.25
SEARCH_OFFSET_M = 2.0


def crop_box_frame(
    points: np.ndarray, box: np.ndarray, scale: float = 1.0, offset_m: float = 0.0
) -> np.ndarray:
    """Points ``(N, C)`` inside ``box`` ``(7,)`` enlarged by ``scale`` and ``offset_m``, expressed
    in the box-local frame -> ``(M, C)`` float32 (extra columns such as intensity pass through).

    Same result, bit for bit, as ``world_to_box(points[points_in_box(points, box, scale,
    offset_m)], box)``, computed column by column in one pass (several times faster).
    """
    pts = np.asarray(points)
    box = np.asarray(box, dtype=np.float64)
    dtype = pts.dtype if np.issubdtype(pts.dtype, np.floating) else np.float64
    # the same float64 arithmetic as world_to_box, then its cast, then points_in_box's test
    c = np.cos(box[..., 6])[..., None]
    s = np.sin(box[..., 6])[..., None]
    dx = pts[:, 0] - box[0:1]
    dy = pts[:, 1] - box[1:2]
    lx = (c * dx + s * dy).astype(dtype, copy=False)
    ly = (-s * dx + c * dy).astype(dtype, copy=False)
    lz = (pts[:, 2] - box[2:3]).astype(dtype, copy=False)
    half = box[3:6] * (0.5 * scale) + offset_m
    mask = np.abs(lx) <= half[0]
    mask &= np.abs(ly) <= half[1]
    mask &= np.abs(lz) <= half[2]
    out = np.empty((int(np.count_nonzero(mask)), pts.shape[1]), dtype=dtype)
    out[:, 0] = lx[mask]
    out[:, 1] = ly[mask]
    out[:, 2] = lz[mask]
    if pts.shape[1] > 3:
        out[:, 3:] = pts[mask, 3:]
    return out.astype(np.float32, copy=False)


def resample(points: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Resample a point set ``(M, C)`` to exactly ``(n, C)`` float32 with ``rng``.

    More than ``n`` points: a random subset without replacement. Fewer: all points plus random
    duplicates. None: zeros. Returns the points and ``M`` (so callers can report empty sets).
    """
    m = len(points)
    if m == 0:
        return np.zeros((n, points.shape[1] if points.ndim == 2 else 3), np.float32), 0
    if m >= n:
        idx = rng.choice(m, size=n, replace=False)
    else:
        idx = np.concatenate([np.arange(m), rng.integers(0, m, size=n - m)])
    return np.take(points, idx, axis=0).astype(np.float32, copy=False), m
