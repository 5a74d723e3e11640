"""Compiled CPU kernels (numba, the ``fast`` extra): the getter that builds them, and the env's
own kernel for its scan indices.

:func:`compiled` turns a builder into a getter that compiles its kernel on first use (cached on
disk by numba) and returns ``None`` without numba, so every caller keeps a numpy / torch path
that computes the same result; :mod:`trackers.kernels` builds the trackers' point ops with it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

__all__ = ["cell_sort_kernel", "compiled", "load_kernels"]


def compiled(build: Callable[[Callable], Callable]) -> Callable[[], Callable | None]:
    """A kernel getter: ``build(njit)`` with numba's ``njit(cache=True, nogil=True)`` on the
    first call (compiled on first use, cached on disk by numba), ``None`` without numba (the
    ``fast`` extra): the callers then run their numpy / torch paths."""

    @functools.cache
    def kernel() -> Callable | None:
        try:
            import numba
        except ImportError:
            return None
        return build(numba.njit(cache=True, nogil=True))

    kernel.__doc__ = build.__doc__
    return kernel


@compiled
def cell_sort_kernel(njit: Callable) -> Callable:
    """The compiled corridor index build of :class:`envs.scan_cache.TrackletScans`: ``(points
    (N, C) float32 C-contiguous, C >= 3, cell_m, ix0, iy0, nx, ny, occupancy (nx * ny,) bool,
    bounds (4,) float32) -> (rows (3, M) float32, firsts (nx * ny + 1,) int64)``.

    A point is kept when its global cell ``floor(float64(x) / cell_m)`` (and y) lies in the
    ``nx x ny`` grid from ``(ix0, iy0)`` on an occupied cell; the kept points' coordinates come
    out sorted by grid-local key ``x * ny + y``, ties in scan order (a counting sort: the
    permutation of numpy's stable argsort), and ``firsts[k]`` is the first row of key ``k``.
    ``bounds = (x_lo, x_hi, y_lo, y_hi)`` is a float32 superset of the grid (``lo <= v < hi``)
    tested before the exact cell, as the numpy path does; one pass over the scan instead of
    a dozen whole-scan array operations."""

    @njit
    def cell_sort(points, cell_m, ix0, iy0, nx, ny, occupancy, bounds):  # pragma: no cover
        n = points.shape[0]
        kept = np.empty(n, np.int64)
        keys = np.empty(n, np.int64)
        counts = np.zeros(nx * ny + 1, np.int64)
        m = 0
        for i in range(n):
            x, y = points[i, 0], points[i, 1]
            if not (bounds[0] <= x < bounds[1] and bounds[2] <= y < bounds[3]):
                continue
            ix = np.int64(np.floor(np.float64(x) / cell_m)) - ix0
            iy = np.int64(np.floor(np.float64(y) / cell_m)) - iy0
            if ix < 0 or ix >= nx or iy < 0 or iy >= ny:
                continue
            key = ix * ny + iy
            if not occupancy[key]:
                continue
            kept[m] = i
            keys[m] = key
            counts[key + 1] += 1
            m += 1
        for k in range(nx * ny):  # counts -> first row of every key
            counts[k + 1] += counts[k]
        rows = np.empty((3, m), np.float32)
        cursor = counts[:-1].copy()
        for j in range(m):  # in scan order: ties keep it
            at = cursor[keys[j]]
            cursor[keys[j]] = at + 1
            i = kept[j]
            rows[0, at] = points[i, 0]
            rows[1, at] = points[i, 1]
            rows[2, at] = points[i, 2]
        return rows, counts

    return cell_sort


def load_kernels() -> bool:
    """Load the env's compiled kernels now (numba's start and its disk cache), e.g. in a parent
    before it forks workers, which inherit them. ``False`` without numba (nothing to load)."""
    kernel = cell_sort_kernel()
    if kernel is None:
        return False
    kernel(np.zeros((1, 4), np.float32), 1.0, 0, 0, 1, 1, np.ones(1, bool), np.ones(4, np.float32))
    return True
