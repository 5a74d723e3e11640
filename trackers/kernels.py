"""Compiled CPU kernels for :mod:`trackers.ops` (numba, the ``fast`` extra).

Each getter (:func:`hash_kernel`, :func:`fps_kernel`, :func:`ball_kernel`, :func:`knn_kernel`,
:func:`nearest_kernel`, and the decision step's :func:`scene_kernel` and
:func:`crop_distance_kernel`; built with :func:`envs.kernels.compiled`) compiles its kernel on
first use (cached on disk by numba) and returns it, or ``None`` without numba: the ops then run
their torch paths.
Every kernel computes what its torch path computes, the float operations in the same order
(squared distances as ``pairwise_sqdist``: ``(dx^2 + dy^2) + dz^2`` in the points' dtype), so
the results are the same bit for bit (tested against the torch paths in ``tests/test_ops.py``);
the one exception, :func:`crop_distance_kernel`, sums its Chamfer means in float64 where torch
sums float32 in its own order: the same crops, the same distances to float32 rounding.
They run only on CPU float32 / float64 coordinates (:func:`compilable`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from envs.kernels import compiled

__all__ = [
    "ball_kernel",
    "compilable",
    "crop_distance_kernel",
    "fps_kernel",
    "hash_kernel",
    "knn_kernel",
    "nearest_kernel",
    "scene_kernel",
]

_MASK32 = 0xFFFFFFFF


def compilable(*points: torch.Tensor) -> bool:
    """Whether the compiled kernels take these point sets: coordinates ``(B, N, 3)`` on the CPU,
    all float32 or all float64 (the dtypes numba computes in as torch does)."""
    dtypes = {p.dtype for p in points}
    return (
        all(p.device.type == "cpu" and p.shape[-1] == 3 for p in points)
        and len(dtypes) == 1
        and dtypes <= {torch.float32, torch.float64}
    )


@compiled
def hash_kernel(njit: Callable) -> Callable:
    """The compiled :func:`trackers.ops.hash_orders` of one cloud ``(xyz (B, N, 3), quantum,
    start, start2, out (B, N) int64)``: the same two hash chains, occurrence ranks and stable
    sorts on unsigned 64-bit integers (32-bit values), so the same orders bit for bit, without
    the ~60 elementwise tensor ops (1.4 ms of a batch-1 ``act``)."""
    m32, one = np.uint64(_MASK32), np.uint64(1)

    @njit
    def hash_rows(xyz, quantum, start, start2, out):  # pragma: no cover - compiled
        # an inner function, not a second @njit one: a dispatcher in the closure pickles
        # differently in every process, so numba's disk cache would miss every time

        def mix32(h):
            h ^= h >> np.uint64(16)
            h = (h * np.uint64(0x85EBCA6B)) & m32
            h ^= h >> np.uint64(13)
            h = (h * np.uint64(0xC2B2AE35)) & m32
            return h ^ (h >> np.uint64(16))

        b, n, _ = xyz.shape
        key = np.empty(n, np.int64)
        final = np.empty(n, np.int64)
        for r in range(b):
            for j in range(n):
                h, h2 = np.uint64(start), np.uint64(start2)
                for c in range(3):
                    q = np.int64(np.rint(np.float64(xyz[r, j, c]) / quantum))
                    q = np.uint64(q & np.int64(_MASK32))
                    h = mix32(h ^ q)
                    h2 = mix32(h2 ^ ((q * np.uint64(0x27D4EB2F)) & m32))
                key[j] = np.int64(((h >> one) << np.uint64(32)) | h2)
            order = np.argsort(key, kind="mergesort")  # stable, as torch.sort(stable=True)
            rank = 0
            for i in range(n):
                k = key[order[i]]
                rank = rank + 1 if i > 0 and k == key[order[i - 1]] else 0
                low, high = np.uint64(k) & m32, np.uint64(k) >> np.uint64(32)
                mixed = (np.uint64(rank + 1) * np.uint64(0x9E3779B1)) & m32
                spread = mix32(mix32(low ^ mixed) ^ high)
                final[i] = np.int64(((spread >> one) << np.uint64(31)) | high)
            second = np.argsort(final, kind="mergesort")
            for i in range(n):
                out[r, i] = order[second[i]]

    return hash_rows


@compiled
def fps_kernel(njit: Callable) -> Callable:
    """The compiled FPS loop ``(xyz (B, N, 3) float ndarray, n, start, out (B, n) int64)``, or
    ``None`` without numba (imported and compiled on first use; cached on disk by numba)."""

    @njit
    def fps_rows(xyz, n, start, out):  # pragma: no cover - compiled
        b, npts, _ = xyz.shape
        mind = np.empty(npts, dtype=xyz.dtype)
        for r in range(b):
            mind[:] = np.inf
            cur = start
            for i in range(n):
                out[r, i] = cur
                cx, cy, cz = xyz[r, cur, 0], xyz[r, cur, 1], xyz[r, cur, 2]
                best, arg = -np.inf, 0
                for j in range(npts):
                    dx, dy, dz = xyz[r, j, 0] - cx, xyz[r, j, 1] - cy, xyz[r, j, 2] - cz
                    m = min(mind[j], dx * dx + dy * dy + dz * dz)
                    mind[j] = m
                    if m > best:  # strictly: the lowest index wins a tie, as argmax
                        best, arg = m, j
                cur = arg

    return fps_rows


@compiled
def ball_kernel(njit: Callable) -> Callable:
    """The compiled ball query ``(xyz (B, N, 3), centres (B, M, 3), r2, k, keep_centres (B, M)
    bool, keep_points (B, N) bool) -> (group (P,), point (P,))`` of
    :func:`trackers.ops.ball_query_pairs` (flat indices; an empty ``(0, 0)`` mask keeps all).
    Per centre it scans the points in index order and stops at the ``k``-th hit, so the pairs
    are the same as the torch paths'; a centre left out is not scanned at all, and a hit on a
    point left out counts towards the ``k`` without being listed (the torch paths' filter after
    the query)."""

    @njit
    def ball_pairs(xyz, centres, r2, k, keep_centres, keep_points):  # pragma: no cover
        b, n, _ = xyz.shape
        m = centres.shape[1]
        all_centres, all_points = keep_centres.shape[0] == 0, keep_points.shape[0] == 0
        group = np.empty(b * m * k, dtype=np.int64)
        point = np.empty(b * m * k, dtype=np.int64)
        p = 0
        for r in range(b):
            for i in range(m):
                if not (all_centres or keep_centres[r, i]):
                    continue
                cx, cy, cz = centres[r, i, 0], centres[r, i, 1], centres[r, i, 2]
                found = 0
                for j in range(n):
                    dx, dy, dz = cx - xyz[r, j, 0], cy - xyz[r, j, 1], cz - xyz[r, j, 2]
                    if dx * dx + dy * dy + dz * dz < r2:
                        if all_points or keep_points[r, j]:
                            group[p], point[p] = r * m + i, r * n + j
                            p += 1
                        found += 1
                        if found == k:
                            break
                if found == 0 and (all_points or keep_points[r, 0]):  # no hit: (centre, 0)
                    group[p], point[p] = r * m + i, r * n
                    p += 1
        return group[:p], point[:p]

    return ball_pairs


@compiled
def knn_kernel(njit: Callable) -> Callable:
    """The compiled :func:`trackers.ops.knn` for coordinates ``(query (B, M, 3), ref (B, N,
    3), sqdist (B, M, k) out, idx (B, M, k) out)``, ``k <= N``: per query the ``k`` smallest
    pairs (squared distance, index) in lexicographic order, which is the stable sort's order
    (ties: lower index first), with ``pairwise_sqdist``'s ``(dx^2 + dy^2) + dz^2``.

    The reference points are sorted by x once per cloud; each query visits them from its own x
    rightwards, then leftwards, inserting into the ``k`` best so far, and leaves a side when
    ``dx^2`` alone exceeds the ``k``-th distance: every point further out is at least that far
    in x, and a sum of non-negative floats never rounds below its first term, so none of them
    could enter (exact; the ``k``-th distance only shrinks). MBPTrack's search regions, per act:
    the backbone's and BPLocNet's kNN 2.9 -> 1.3 ms. (Alternating the sides nearest-first
    visits fewer points but mispredicts its choice: slower, as was a scan of every point.)"""

    @njit
    def knn_rows(query, ref, sqdist, idx):  # pragma: no cover - compiled
        b, m, _ = query.shape
        n, k = ref.shape[1], idx.shape[2]
        xs, ys, zs = np.empty(n, ref.dtype), np.empty(n, ref.dtype), np.empty(n, ref.dtype)
        for r in range(b):
            order = np.argsort(ref[r, :, 0], kind="mergesort")
            for s in range(n):
                xs[s], ys[s], zs[s] = ref[r, order[s], 0], ref[r, order[s], 1], ref[r, order[s], 2]
            for i in range(m):
                qx, qy, qz = query[r, i, 0], query[r, i, 1], query[r, i, 2]
                dist, near = sqdist[r, i], idx[r, i]
                filled = 0
                start = np.searchsorted(xs, qx)
                for side in range(2):  # rightwards from the query's x, then leftwards
                    s, step = (start, 1) if side == 0 else (start - 1, -1)
                    while 0 <= s < n:
                        dx = qx - xs[s]
                        if filled == k and dx * dx > dist[k - 1]:
                            break
                        dy, dz = qy - ys[s], qz - zs[s]
                        d = dx * dx + dy * dy + dz * dz
                        j = order[s]
                        s += step
                        if filled < k:
                            pos = filled
                            filled += 1
                        elif d < dist[k - 1] or (d == dist[k - 1] and j < near[k - 1]):
                            pos = k - 1
                        else:
                            continue
                        while pos > 0 and (
                            dist[pos - 1] > d or (dist[pos - 1] == d and near[pos - 1] > j)
                        ):
                            dist[pos], near[pos] = dist[pos - 1], near[pos - 1]
                            pos -= 1
                        dist[pos], near[pos] = d, j

    return knn_rows


@compiled
def nearest_kernel(njit: Callable) -> Callable:
    """The compiled :func:`trackers.ops.nearest_distances` before its square roots: ``(a (K, U,
    3), a_in (K, U) bool, b (V, 3), a_near (K, U) out, b_near (K, V) out)``, every pair's
    squared distance as ``pairwise_sqdist`` computes it and the minima over the other set (a
    point outside its set: ``inf``, as the torch path's ``+ inf`` penalty). The caller takes
    the square roots with torch: its ``sqrt`` is not IEEE-rounded in every case (MKL), so
    numpy's would differ in the last bit."""

    @njit
    def nearest_rows(a, a_in, b, a_near, b_near):  # pragma: no cover - compiled
        k, u, _ = a.shape
        v = b.shape[0]
        inf = a.dtype.type(np.inf)
        b_near[:] = inf
        for s in range(k):
            for i in range(u):
                best = inf
                if a_in[s, i]:
                    ax, ay, az = a[s, i, 0], a[s, i, 1], a[s, i, 2]
                    for j in range(v):
                        dx, dy, dz = ax - b[j, 0], ay - b[j, 1], az - b[j, 2]
                        d = dx * dx + dy * dy + dz * dz
                        if d < best:
                            best = d
                        if d < b_near[s, j]:
                            b_near[s, j] = d
                a_near[s, i] = best

    return nearest_rows


@compiled
def scene_kernel(njit: Callable) -> Callable:
    """The decision step's view of one observation (:class:`trackers.decision.Scene`) in one
    pass: ``(search (N, 3) float32, search_bits (N, 3) int32, crops (2, L, 3) float32,
    crop_bits (2, L, 3) int32, floor (1,), real (N,) bool out, points (N, 3) out, layout (N,)
    int64 out, weights (N,) int64 out, crop_masks (2, L) bool out, crop_points (2, L, 3) out,
    crop_layouts (2, L) int64 out, crop_weights (2, L) int64 out, counts (5,) int64 out)``.
    ``real``: the search's rows that are not zero padding; ``crop_masks``: the crops' points
    above ``floor`` (as ``_above_ground``; ``counts[3 + k]`` of them in crop ``k``); then, as
    :func:`trackers.ops.distinct_points`, the distinct masked points of the search and of each
    crop (``points[:counts[0]]``, ``crop_points[k, :counts[1 + k]]``), each masked row's
    distinct point (``layout``; the count for the others) and how many masked rows each
    distinct point stands for (``weights``, ``crop_weights``): the rows in order, a point new
    where no earlier row has its three bits (an open-addressing hash table on them, one pass
    where a sort took ~40 % of the kernel). The same sets as the torch ops (in order of first
    row, where the torch ops sort; no consumer reads the order), without their ~40 small tensor
    ops per observation."""
    spread = (
        np.uint64(0x9E3779B97F4A7C15),  # odd 64-bit constants: multiplicative hashing
        np.uint64(0xC2B2AE3D27D4EB4F),
        np.uint64(0x165667B19E3779F9),
    )
    m32 = np.uint64(_MASK32)

    @njit
    def scene_rows(
        search,
        search_bits,
        crops,
        crop_bits,
        floor,
        real,
        points,
        layout,
        weights,
        crop_masks,
        crop_points,
        crop_layouts,
        crop_weights,
        counts,
    ):  # pragma: no cover - compiled
        def distinct(xyz, bits, mask, out, out_layout, out_weights):
            n, shift = bits.shape[0], np.uint64(63)
            while (np.uint64(1) << (np.uint64(64) - shift)) < 2 * n:  # a table of >= 2n slots
                shift -= np.uint64(1)
            slots = np.int64(1) << np.int64(np.uint64(64) - shift)
            table = np.full(slots, -1, np.int64)  # each slot's distinct point, or -1
            first = np.empty(n, np.int64)  # each distinct point's first row
            u = 0
            for i in range(n):
                if not mask[i]:
                    out_layout[i] = -1
                    continue
                key = np.uint64(bits[i, 0]) & m32
                key = key * spread[0] ^ (np.uint64(bits[i, 1]) & m32) * spread[1]
                key ^= (np.uint64(bits[i, 2]) & m32) * spread[2]
                slot = np.int64(key >> shift)
                while True:
                    d = table[slot]
                    if d < 0:  # a new point
                        table[slot], first[u] = u, i
                        out[u, 0], out[u, 1], out[u, 2] = xyz[i, 0], xyz[i, 1], xyz[i, 2]
                        out_layout[i], out_weights[u] = u, 1
                        u += 1
                        break
                    r = first[d]
                    if bits[r, 0] == bits[i, 0] and bits[r, 1] == bits[i, 1]:
                        if bits[r, 2] == bits[i, 2]:  # a copy
                            out_layout[i] = d
                            out_weights[d] += 1
                            break
                    slot = (slot + 1) & (slots - 1)
            for i in range(n):
                if out_layout[i] < 0:
                    out_layout[i] = u
            return u

        zero = search.dtype.type(0)
        for i in range(search.shape[0]):
            real[i] = search[i, 0] != zero or search[i, 1] != zero or search[i, 2] != zero
        counts[0] = distinct(search, search_bits, real, points, layout, weights)
        for k in range(2):
            counts[3 + k] = 0
            for j in range(crops.shape[1]):
                x, y, z = crops[k, j, 0], crops[k, j, 1], crops[k, j, 2]
                crop_masks[k, j] = (x != zero or y != zero or z != zero) and z > floor[0]
                counts[3 + k] += crop_masks[k, j]
            counts[1 + k] = distinct(
                crops[k], crop_bits[k], crop_masks[k], crop_points[k], crop_layouts[k],
                crop_weights[k],
            )  # fmt: skip

    return scene_rows


@compiled
def crop_distance_kernel(njit: Callable) -> Callable:
    """The decision step's crops and Chamfer distances of one observation against template
    crops (the re-ranking's candidates against the first crop; the still-target test's
    reference box against the first and the previous), every candidate box and crop in one
    pass (:func:`trackers.decision._compiled_crop_distances`): ``(points (U, 3), weights (U,),
    cos (C,), sin (C,), centres (C, 3), half (3,), floor (1,), crops (T, L, 3), crop_counts
    (T,), crop_weights (T, L), crop_masked (T,), distances (T, C) out, boxed (C,) int64
    out)``: the search's distinct points and how many rows each stands for (``weights``,
    :func:`scene_kernel`), template crop ``t``'s distinct points ``crops[t, :crop_counts[t]]``
    with their weights, standing for ``crop_masked[t]`` rows. Each distinct search point in
    each candidate's frame with the float operations of ``world_to_box_torch`` in their order
    (``c dx + s dy``, ``-s dx + c dy``, ``dz``), inside the candidate's crop as ``_crop_mask``
    tests it (``|x| <= half``, not the origin, ``z > floor``); then, as
    :func:`nearest_kernel`, the squared distances between the crop's points and the template
    crop's, and the symmetric Chamfer distance over rows as :func:`trackers.ops.layout_mean`
    weighs it (the mean over the search's boxed rows of their nearest distances, and over the
    template crop's masked rows, halved; ``inf`` for an empty crop), each distinct point
    counted as often as its rows, and how many rows each candidate's crop holds (``boxed``).
    The sums run in float64, so the distances equal the torch ops' to float32 rounding (their
    sums' order is torch's own), without their ~40 small tensor ops per observation."""

    @njit
    def crop_distances(
        points,
        weights,
        cos,
        sin,
        centres,
        half,
        floor,
        crops,
        crop_counts,
        crop_weights,
        crop_masked,
        distances,
        boxed,
    ):  # pragma: no cover - compiled
        t_count, c_count = distances.shape
        u = points.shape[0]
        inf, zero = points.dtype.type(np.inf), points.dtype.type(0)
        in_crop = np.empty(u, np.bool_)
        moved = np.empty((u, 3), points.dtype)  # the points in the candidate's frame
        crop_near = np.empty(crops.shape[1], points.dtype)
        for c in range(c_count):
            co, si, nsi = cos[c], sin[c], -sin[c]
            count = 0
            for i in range(u):
                dx = points[i, 0] - centres[c, 0]
                dy = points[i, 1] - centres[c, 1]
                z = points[i, 2] - centres[c, 2]
                x = co * dx + si * dy
                y = nsi * dx + co * dy
                in_crop[i] = (
                    abs(x) <= half[0]
                    and abs(y) <= half[1]
                    and abs(z) <= half[2]
                    and (x != zero or y != zero or z != zero)
                    and z > floor[0]
                )
                moved[i, 0], moved[i, 1], moved[i, 2] = x, y, z
                if in_crop[i]:
                    count += weights[i]
            boxed[c] = count
            for t in range(t_count):
                f = crop_counts[t]
                if count == 0 or crop_masked[t] == 0:  # an empty crop: no distance
                    distances[t, c] = inf
                    continue
                crop_near[:f] = inf
                to_crop = 0.0  # float64 sums of float32 square roots, weighted by rows
                for i in range(u):
                    if not in_crop[i]:
                        continue
                    # nearest_kernel's loop, repeated: a kernel that called another compiled
                    # one would hold a dispatcher in its closure, which misses numba's disk
                    # cache in every process (see hash_kernel)
                    best = inf
                    x, y, z = moved[i, 0], moved[i, 1], moved[i, 2]
                    for j in range(f):
                        ex, ey, ez = x - crops[t, j, 0], y - crops[t, j, 1], z - crops[t, j, 2]
                        d = ex * ex + ey * ey + ez * ez
                        if d < best:
                            best = d
                        if d < crop_near[j]:
                            crop_near[j] = d
                    to_crop += weights[i] * np.sqrt(best)
                to_search = 0.0
                for j in range(f):
                    to_search += crop_weights[t, j] * np.sqrt(crop_near[j])
                search_to_crop = points.dtype.type(to_crop / count)
                crop_to_search = points.dtype.type(to_search / crop_masked[t])
                distances[t, c] = points.dtype.type(0.5) * (search_to_crop + crop_to_search)

    return crop_distances
