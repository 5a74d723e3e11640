"""Cropping and resampling of point sets: the one implementation behind the env's observations
and the supervised training samples (so that what a tracker is trained on is what it sees).

The sets are small (tens to hundreds of points per crop), so the cost is numpy's per-call
overhead more than arithmetic: the kernels keep the number of numpy calls low, work on
coordinate rows ``(3, N)`` (contiguous inner loops, where ``(N, 3)`` against a ``(3,)``
broadcast loops over rows of three), and :func:`resample_into` draws the random duplicates of
several sets at once.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import gymnasium as gym
import numpy as np

from envs.spec import (
    DEFAULT_MEMORY_FRAMES,
    MEMORY_KEYS,
    OBS_SHAPES,
    OPTIONAL_OBS_SHAPES,
    PREVIOUS_SEARCH_CHANNELS,
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    SEARCH_SIZE,
    TEMPLATE_ENLARGEMENT,
    TEMPLATE_SCALE,
    TEMPLATE_SIZE,
)

__all__ = [
    "CURRENT_MASK",
    "CURRENT_TIME",
    "MASK_GT",
    "MASK_PREDICTED",
    "MOTION_BOUND_M",
    "POINT_BOUND_M",
    "PREVIOUS_SEARCH_CHANNELS",
    "PREVIOUS_TIME",
    "SEARCH_OFFSET_M",
    "SEARCH_SCALE",
    "SEARCH_SIZE",
    "SIZE_BOUND_M",
    "TEMPLATE_SCALE",
    "TEMPLATE_SIZE",
    "box_frame",
    "crop_box_frame",
    "crop_extents",
    "crop_parts",
    "extent_threshold",
    "in_extent",
    "observation_space",
    "previous_search_points",
    "random_words",
    "resample",
    "resample_into",
    "uniform_indices",
]

PREVIOUS_TIME = 0.0
CURRENT_TIME = 0.1
"""Time channel of the previous frame's points, and the value M2-Track gives the current
frame's (``search``) points when a tracker merges the two."""
MASK_GT = (0.0, 1.0)
MASK_PREDICTED = (0.2, 0.8)
CURRENT_MASK = 0.5
"""Previous-box mask values ``(outside, inside)`` when the previous box is the ground truth
and when it is a prediction (M2-Track's softened prior), and the value M2-Track gives the
current frame's points."""

POINT_BOUND_M = 100.0
"""Bound of the point observation spaces (metres, box frame); crops never reach it for boxes
smaller than ~150 m."""
SIZE_BOUND_M = 100.0
"""Bound of the ``size`` space and of a served box's size (m)."""
MOTION_BOUND_M = 100.0
"""Bound of the ``motion`` space's translation (m); the rotation's is pi."""

_LOW_HALF = 0 if sys.byteorder == "little" else 1  # of a uint64 viewed as two uint32
_HIGH_SHIFT = np.uint64(32)
_SIGNS = np.array([[1.0], [-1.0]])  # (s, -s) as s * _SIGNS: exact, cheaper than np.array


def crop_extents(box: np.ndarray, enlargements: Sequence[tuple[float, float]]) -> np.ndarray:
    """Half extents of ``box`` ``(7,)`` enlarged by each ``(scale, offset_m)``, as columns
    ``(3, K)`` float64 (one broadcasts over ``(3, N)`` coordinates): ``points_in_box``'s
    ``size * (0.5 * scale) + offset_m``, in Python floats (the same IEEE double arithmetic,
    without numpy's per-call cost)."""
    size = np.asarray(box, dtype=np.float64)[3:6].tolist()
    return np.array([[v * (0.5 * scale) + off for scale, off in enlargements] for v in size])


def box_frame(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Coordinates ``(3, N)`` (rows x, y, z; any strides) in the box-local frame of ``box``
    ``(7,)`` float64 -> ``(3, N)`` in their float dtype (float64 for integers).

    Bit for bit ``world_to_box``: the same float64 arithmetic, rounded once to the dtype.
    """
    dtype = xyz.dtype if xyz.dtype.kind == "f" else np.dtype(np.float64)
    c, s = np.cos(box[6]), np.sin(box[6])
    d = xyz - box[:3, None]  # float64 (dx, dy, dz)
    # both rotated rows in three array operations: (c dx, c dy) + (s dy, -s dx), the second
    # exactly world_to_box's -(s dx) (a sign flip rounds symmetrically; a + -b is a - b)
    np.add(d[:2] * c, d[1::-1] * (s * _SIGNS), out=d[:2])
    # one cast at the end: casting inside each operation costs more than the operation
    return d.astype(dtype, copy=False)


def extent_threshold(half: np.ndarray, dtype: np.dtype | type) -> np.ndarray:
    """Half extents (float64) -> the largest values of ``dtype`` not above them: for
    coordinates ``x`` of that dtype, ``|x| <= threshold`` exactly when ``|x| <= half`` in
    float64 (``points_in_box``'s comparison), without a slower mixed-type comparison."""
    threshold = half.astype(dtype)
    np.nextafter(threshold, -np.inf, out=threshold, where=threshold > half)
    return threshold


def in_extent(local: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Mask ``(N,)`` of box-frame coordinates ``(3, N)`` within ``threshold`` ``(3, 1)`` or
    ``(3, N)`` (see :func:`extent_threshold`; boundary included)."""
    inside = np.abs(local) <= threshold
    mask = inside[0] & inside[1]
    mask &= inside[2]
    return mask


def crop_parts(local: np.ndarray, threshold: np.ndarray, widths: Sequence[int]) -> list[np.ndarray]:
    """Split box-frame coordinates ``(3, N)`` into consecutive parts of ``widths`` points and
    keep, in each, the points within ``threshold`` (see :func:`in_extent`) -> ``(M_i, 3)``
    float32 per part (views of one array: one selection for all parts)."""
    mask = in_extent(local, threshold)
    # select along the contiguous axis, then transpose: faster than boolean rows of local.T
    selected = np.ascontiguousarray(local.compress(mask, axis=1).T, dtype=np.float32)
    parts, first, start = [], 0, 0
    for width in widths[:-1]:
        stop = first + int(np.count_nonzero(mask[start : start + width]))
        parts.append(selected[first:stop])
        first, start = stop, start + width
    parts.append(selected[first:])
    return parts


def crop_box_frame(
    points: np.ndarray, box: np.ndarray, scale: float = 1.0, offset_m: float = 0.0
) -> np.ndarray:
    """Points ``(N, C)`` inside ``box`` ``(7,)`` enlarged by ``scale`` and ``offset_m``, expressed
    in the box-local frame -> ``(M, C)`` float32 (extra columns such as intensity pass through).

    Same result, bit for bit, as ``world_to_box(points[points_in_box(points, box, scale,
    offset_m)], box)``: :func:`box_frame` (world_to_box's float64 arithmetic, then its cast),
    then points_in_box's test (:func:`in_extent`).
    """
    pts = np.asarray(points)
    box = np.asarray(box, dtype=np.float64)
    # coordinate rows made contiguous first: the strided view would slow every step below
    local = box_frame(np.ascontiguousarray(pts[:, :3].T), box)
    threshold = extent_threshold(crop_extents(box, [(scale, offset_m)]), local.dtype)
    if pts.shape[1] == 3:
        return crop_parts(local, threshold, [len(pts)])[0]
    mask = in_extent(local, threshold)
    out = np.empty((int(np.count_nonzero(mask)), pts.shape[1]), dtype=local.dtype)
    out[:, :3] = local.T[mask]
    out[:, 3:] = pts[mask, 3:]
    return out.astype(np.float32, copy=False)


_RAW64 = (np.random.PCG64, np.random.PCG64DXSM, np.random.Philox, np.random.SFC64)
"""Bit generators whose raw draws are 64 random bits (MT19937's are 32)."""


def random_words(bit_generator: np.random.BitGenerator, n: int) -> np.ndarray:
    """``n`` independent uniform 32-bit words ``(n,)`` uint32 from ``bit_generator``'s raw
    draws: both halves of each 64-bit draw where the generator has them (half the draws, as
    numpy's own 32-bit sampling does), else the low 32 bits of each draw."""
    if isinstance(bit_generator, _RAW64):
        return bit_generator.random_raw((n + 1) // 2).view(np.uint32)[:n]
    return bit_generator.random_raw(n).astype(np.uint32)


def uniform_indices(
    rng: np.random.Generator, bounds: np.ndarray, top: int | None = None
) -> np.ndarray:
    """Independent integers ``(K,)`` int64, the ``i``-th exactly uniform in ``[0, bounds[i])``
    (``1 <= bounds[i] <= 2**32``), from ``rng``'s bit generator; ``top``: an upper bound of the
    bounds (saves their maximum when the caller knows one). int64 is numpy's index type:
    ``take`` reads the result without converting it.

    Lemire's multiply-shift with rejection on 32-bit words (:func:`random_words`), vectorised:
    ``Generator.integers`` costs ~15 us a call whatever the size, this one a few us for any
    number of bounds.
    """
    bounds = np.asarray(bounds, dtype=np.uint64)
    n = len(bounds)
    prod = np.multiply(random_words(rng.bit_generator, n), bounds)  # uint64
    words = prod.view(np.uint32)  # low and high 32-bit halves of the products, interleaved
    low = words[_LOW_HALF::2]
    # A low word below 2**32 mod bound (< bound) marks an over-weighted result: redraw it.
    # Only low words below the bound can be (p < bound / 2**32). The n high words all are below
    # ``top`` (< bound <= top), so some low word is exactly when more than n words are: one
    # contiguous test instead of one on the strided low words.
    if np.count_nonzero(words < (int(bounds.max()) if top is None else top)) > n:
        check = (low < bounds).nonzero()[0]
        while len(check):
            reject = check[low[check] < np.uint64(1 << 32) % bounds[check]]
            redraw = random_words(rng.bit_generator, len(reject))
            prod[reject] = np.multiply(redraw, bounds[reject])
            check = reject[low[reject] < bounds[reject]]
    return (prod >> _HIGH_SHIFT).view(np.int64)  # the high words


def resample_into(
    point_sets: Sequence[np.ndarray], outs: Sequence[np.ndarray], rng: np.random.Generator
) -> list[int]:
    """Resample every ``point_sets[i]`` ``(M_i, C)`` array into ``outs[i]`` ``(n_i, C)`` float32
    (filled in place) with ``rng``; returns the ``M_i`` (so callers can report empty sets).

    More than ``n`` points: a random subset without replacement, in random order. Fewer: all
    points in order, then uniform random duplicates (drawn for all sets at once: the
    ``Generator`` call costs more than the draws). None: zeros.
    """
    counts = [len(p) for p in point_sets]
    pads = [len(o) - m if 0 < m < len(o) else 0 for m, o in zip(counts, outs, strict=True)]
    bounds = np.array(counts, np.uint64).repeat(pads) if sum(pads) else None
    dups = None if bounds is None else uniform_indices(rng, bounds, max(counts))
    pos = 0
    for points, out, m, pad in zip(point_sets, outs, counts, pads, strict=True):
        # indices are in range by construction: "clip" skips take's checked, buffered path
        if m == 0:
            out.fill(0.0)
        elif pad == 0:  # a permutation's prefix: a uniform ordered subset (~3x cheaper
            # than Generator.choice(replace=False), whose argument handling dominates here)
            points.take(rng.permutation(m)[: len(out)], axis=0, out=out, mode="clip")
        else:
            out[:m] = points
            points.take(dups[pos : pos + pad], axis=0, out=out[m:], mode="clip")
            pos += pad
    return counts


def resample(points: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Resample a point set ``(M, C)`` to exactly ``(n, C)`` float32 with ``rng`` (see
    :func:`resample_into`). Returns the points and ``M``."""
    points = np.asarray(points, dtype=np.float32)
    out = np.empty((n, points.shape[1] if points.ndim == 2 else 3), np.float32)
    return out, resample_into([points], [out], rng)[0]


def observation_space(
    keys: Sequence[str], memory_frames: int = DEFAULT_MEMORY_FRAMES
) -> gym.spaces.Dict:
    """The env's observation space for ``keys`` (the default keys plus any opt-in ones, see
    :data:`envs.spec.OBS_SHAPES`; the memory keys with ``memory_frames`` slots): float32 boxes
    with finite bounds."""
    motion_hi = np.array([MOTION_BOUND_M] * 3 + [np.pi], dtype=np.float32)
    bounds = {
        "template": (-POINT_BOUND_M, POINT_BOUND_M),
        "search": (-POINT_BOUND_M, POINT_BOUND_M),
        "size": (0.0, SIZE_BOUND_M),
        "motion": (-motion_hi, motion_hi),
    }
    space = gym.spaces.Dict(
        {k: gym.spaces.Box(*bounds[k], OBS_SHAPES[k], np.float32) for k in OBS_SHAPES}
    )
    if "previous_search" in keys:
        shape = OPTIONAL_OBS_SHAPES["previous_search"]
        hi = np.array([POINT_BOUND_M] * 3 + [1.0, 1.0], np.float32)
        lo = np.array([-POINT_BOUND_M] * 3 + [0.0, 0.0], np.float32)
        space["previous_search"] = gym.spaces.Box(
            np.tile(lo, (shape[0], 1)), np.tile(hi, (shape[0], 1)), shape, np.float32
        )
    for key, box in _memory_spaces(memory_frames).items():
        if key in keys:
            space[key] = box
    return space


def _memory_spaces(frames: int) -> dict[str, gym.spaces.Box]:
    """The spaces of :data:`envs.spec.MEMORY_KEYS` with ``frames`` slots: points and box
    centres within :data:`POINT_BOUND_M`, masks and valid flags in ``[0, 1]``, yaws in
    ``[-pi, pi]``."""
    bound = POINT_BOUND_M
    lo_p = np.tile(np.array([-bound] * 3 + [0.0], np.float32), (frames, SEARCH_SIZE, 1))
    hi_p = np.tile(np.array([bound] * 3 + [1.0], np.float32), (frames, SEARCH_SIZE, 1))
    lo_b = np.tile(np.array([-bound] * 3 + [-np.pi, 0.0], np.float32), (frames, 1))
    hi_b = np.tile(np.array([bound] * 3 + [np.pi, 1.0], np.float32), (frames, 1))
    boxes = (
        gym.spaces.Box(lo_p, hi_p, lo_p.shape, np.float32),
        gym.spaces.Box(lo_b, hi_b, lo_b.shape, np.float32),
    )
    return dict(zip(MEMORY_KEYS, boxes, strict=True))


def previous_search_points(
    xyz: np.ndarray, ref: np.ndarray, count: int, certain: bool
) -> np.ndarray:
    """The ``previous_search`` observation ``(SEARCH_SIZE, 5)`` float32 from its resampled
    points ``xyz`` ``(SEARCH_SIZE, 3)`` (reference box frame, m) of ``count`` distinct crop
    points (0: zeros): the time column (:data:`PREVIOUS_TIME`) and the previous-box mask, 1 / 0
    inside / outside ``ref`` ``(7,)`` scaled by the template scale when that box is
    ``certain`` (the previous frame's ground truth), else M2-Track's softened 0.8 / 0.2."""
    out = np.zeros((len(xyz), len(PREVIOUS_SEARCH_CHANNELS)), np.float32)
    if count == 0:
        return out
    out[:, :3] = xyz
    out[:, 3] = PREVIOUS_TIME
    outside, inside = MASK_GT if certain else MASK_PREDICTED
    threshold = extent_threshold(crop_extents(ref, [TEMPLATE_ENLARGEMENT]), np.float32)
    out[:, 4] = np.where(in_extent(xyz.T, threshold), inside, outside)
    return out
