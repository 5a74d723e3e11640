"""Cropping and resampling of point sets: the one implementation behind the env's observations
and the supervised training samples (so that what a tracker is trained on is what it sees).
"""

from __future__ import annotations

import numpy as np

from envs.geometry import points_in_box, world_to_box

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
    """
    mask = points_in_box(points[:, :3], box, scale=scale, offset_m=offset_m)
    return world_to_box(points[mask], box).astype(np.float32, copy=False)


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
    return np.ascontiguousarray(points[idx], dtype=np.float32), m
