"""Point-set operations in torch, batched over a leading dimension (with the ``fast`` extra
some run as compiled CPU kernels, :mod:`trackers.kernels`, with the same results).

Shapes: ``B`` batch, ``N`` points, ``M`` query points (centres), ``k`` neighbours, ``C`` channels.
Indices are ``int64``. Every op gives the same result on CPU and GPU (the orderings below are
integer or comparison based; distances are computed the same way on both).

* sampling: :func:`random_order` (a ``torch.Generator``), :func:`hash_order` (deterministic and
  independent of the input order), :func:`farthest_point_sample`;
* neighbourhoods: :func:`ball_query` (PointNet++ semantics; :func:`ball_query_pairs` lists its
  real hits), :func:`knn` (any dimension: coordinates or features), :func:`pairwise_sqdist`;
* set distances: :func:`chamfer_distance` between masked point sets;
* indexing: :func:`gather` / :func:`group`; copies of a point: :func:`first_copy`; distinct
  rows: :func:`unique_rows`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import torch

from trackers import kernels

__all__ = [
    "ball_query",
    "ball_query_pairs",
    "chamfer_distance",
    "distinct_points",
    "farthest_point_sample",
    "first_copy",
    "first_copy_or_none",
    "gather",
    "group",
    "hash_order",
    "hash_orders",
    "knn",
    "layout_mean",
    "load_kernels",
    "nearest_distances",
    "pairwise_sqdist",
    "random_order",
    "unique_rows",
]

_MASK32 = 0xFFFFFFFF


def gather(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Gather rows: ``points (B, N, C)``, ``idx (B, *S)`` -> ``(B, *S, C)``.

    One ``index_select`` on the flattened rows: on CPU its backward (``index_add_``) is about 5x
    faster than that of ``torch.gather`` or advanced indexing (a scatter / sorted ``index_put_``).
    """
    b, n, c = points.shape
    offset = (torch.arange(b, device=idx.device) * n).view(b, *([1] * (idx.dim() - 1)))
    out = points.reshape(b * n, c).index_select(0, (idx + offset).reshape(-1))
    return out.reshape(*idx.shape, c)


def group(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Group neighbours: ``points (B, N, C)``, ``idx (B, M, k)`` -> ``(B, M, k, C)``."""
    return gather(points, idx)


def pairwise_sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances ``a (B, M, C)``, ``b (B, N, C)`` -> ``(B, M, N)``.

    Computed from coordinate differences (not ``|a|^2 + |b|^2 - 2ab``), so it is exact to float
    rounding and never negative; the same formula is used by the brute-force test references.
    """
    if a.shape[-1] <= 4:  # coordinates: explicit differences, cheap at C = 3
        # coordinate-major copies: the broadcast differences then read contiguous rows
        at, bt = a.transpose(1, 2).contiguous(), b.transpose(1, 2).contiguous()  # (B, C, M|N)
        d = at[:, 0, :, None] - bt[:, 0, None, :]
        out = d * d
        in_place = not (torch.is_grad_enabled() and (a.requires_grad or b.requires_grad))
        for c in range(1, a.shape[-1]):
            if in_place:  # one buffer, no allocation per step: the same operations and rounding
                torch.sub(at[:, c, :, None], bt[:, c, None, :], out=d)
                out.add_(d.mul_(d))
            else:
                d = at[:, c, :, None] - bt[:, c, None, :]
                out = out + d * d
        return out
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist").square()


def random_order(
    batch: int, n: int, generator: torch.Generator | None = None, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """A random permutation of ``range(n)`` per batch row -> ``(B, n)`` int64.

    Drawn on the generator's device (CPU when ``generator`` is None: a fresh default-seeded
    CPU generator is NOT used; pass one for reproducibility) and moved to ``device``.
    """
    gen_device = generator.device if generator is not None else torch.device("cpu")
    keys = torch.rand(batch, n, generator=generator, device=gen_device)
    return keys.argsort(dim=1).to(device)


def _mul32(h: torch.Tensor, c: int) -> torch.Tensor:
    """``(h * c) mod 2**32`` for int64 tensors holding 32-bit values, without int64 overflow."""
    lo = h * (c & 0xFFFF)  # < 2**48
    hi = ((h * (c >> 16)) & 0xFFFF) << 16  # the high half's contribution mod 2**32
    return (lo + hi) & _MASK32


def _mix32(h: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer finaliser (murmur3 fmix32) on int64 tensors holding 32-bit values."""
    h = h ^ (h >> 16)
    h = _mul32(h, 0x85EBCA6B)
    h = h ^ (h >> 13)
    h = _mul32(h, 0xC2B2AE35)
    return h ^ (h >> 16)


def hash_order(xyz: torch.Tensor, seed: int = 0, quantum: float = 1e-4) -> torch.Tensor:
    """A pseudo-random but deterministic order of the points ``xyz (B, N, 3)`` -> ``(B, N)``.

    Each point gets a 63-bit key from a hash of its coordinates (quantised to ``quantum`` metres),
    of ``seed`` and of its occurrence rank among identical points (so the copies of a duplicated
    point - the env pads small clouds with duplicates - are spread through the order like a
    random permutation would, instead of being bunched together); points are sorted by key.
    The sequence of points this order produces does not depend on the order the points came in,
    so a prefix is a random sample invariant to input permutations. (Distinct points closer than
    ``quantum`` are treated as copies of one point: the only case where input order can matter.)
    """
    return hash_orders([xyz], [seed], quantum)[0]


def hash_orders(
    clouds: Sequence[torch.Tensor], seeds: Sequence[int], quantum: float = 1e-4
) -> list[torch.Tensor]:
    """:func:`hash_order` of each cloud ``(B, N_i, 3)`` with its seed -> ``[(B, N_i)]``, the
    same orders bit for bit, hashed side by side (one pass of the elementwise hash, which is
    most of the cost at batch 1; on CPU with the ``fast`` extra one compiled loop per cloud,
    :func:`trackers.kernels.hash_kernel`)."""
    starts = [(seed * 0x9E3779B1 + 0x7F4A7C15) & _MASK32 for seed in seeds]
    starts2 = [(seed * 0x85EBCA77 + 0x165667B1) & _MASK32 for seed in seeds]
    kernel = kernels.hash_kernel() if kernels.compilable(*clouds) else None
    if kernel is not None:
        orders = []
        for cloud, start, start2 in zip(clouds, starts, starts2, strict=True):
            out = torch.empty(cloud.shape[:2], dtype=torch.long)
            kernel(cloud.detach().contiguous().numpy(), float(quantum), start, start2, out.numpy())
            orders.append(out)
        return orders
    sizes = [c.shape[1] for c in clouds]
    xyz = torch.cat(list(clouds), dim=1)
    dev = xyz.device
    q = (torch.round(xyz.double() / quantum).long() & _MASK32).movedim(-1, 0)  # (3, B, N)
    # two independent 32-bit hash chains, run side by side (chain, B, N): half the small ops
    inputs = torch.stack([q, _mul32(q, 0x27D4EB2F)], dim=1)  # (3, 2, B, N)
    size = torch.tensor(sizes, device=dev)
    h = torch.stack([torch.tensor(starts, device=dev), torch.tensor(starts2, device=dev)])
    h = h.repeat_interleave(size, dim=1, output_size=xyz.shape[1])[:, None, :]  # (2, 1, N)
    for c in range(inputs.shape[0]):
        h = _mix32(h ^ inputs[c])
    key = ((h[0] >> 1) << 32) | h[1]  # 63 bits: coordinates collide with probability ~1e-13
    segment = None  # the cloud of each point (one cloud: not needed)
    if len(sizes) > 1:
        segment = torch.arange(len(sizes), device=dev).repeat_interleave(size).expand_as(key)
    key, order = _sort_within(key, segment)
    # occurrence rank of each point within its run of identical keys (runs end at clouds' ends)
    pos = torch.arange(key.shape[1], device=dev).expand_as(key)
    run = torch.ones_like(key, dtype=torch.bool)
    run[:, 1:] = key[:, 1:] != key[:, :-1]
    if segment is not None:
        run |= segment != torch.roll(segment, 1, dims=1)
    rank = pos - torch.where(run, pos, torch.zeros_like(pos)).cummax(dim=1).values
    spread = _mix32(_mix32((key & _MASK32) ^ _mul32(rank + 1, 0x9E3779B1)) ^ (key >> 32))
    final = ((spread >> 1) << 31) | (key >> 32)  # rank-spread high bits, coordinates as tie-break
    order = torch.gather(order, 1, _sort_within(final, segment)[1])
    offsets = [0, *itertools.accumulate(sizes)]
    return [order[:, a:b] - a for a, b in itertools.pairwise(offsets)]


def _sort_within(
    key: torch.Tensor, segment: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Stable sort of ``key (B, N)`` within the consecutive segments ``segment (B, N)`` (sorted
    values and indices; ``None``: one segment): by key, then stably by segment."""
    key, order = torch.sort(key, dim=1, stable=True)
    if segment is not None:
        by_segment = torch.sort(segment.gather(1, order), dim=1, stable=True).indices
        key, order = key.gather(1, by_segment), order.gather(1, by_segment)
    return key, order


def first_copy(xyz: torch.Tensor) -> torch.Tensor:
    """Index of the first point with the same coordinates (bit for bit): ``xyz (B, N, 3)`` ->
    ``(B, N)`` int64, ``first_copy[b, j] <= j`` (``j`` itself for a point's first occurrence).

    Two stable sorts (by ``z``, then by ``(x, y)``) put copies next to each other in index order,
    so each run starts at its lowest index.
    """
    bits = xyz.contiguous().view(torch.int32).long() & _MASK32  # (B, N, 3)
    order = torch.sort(bits[..., 2], dim=1, stable=True).indices
    xy = (bits[..., 0] << 32) | bits[..., 1]
    order = order.gather(1, torch.sort(xy.gather(1, order), dim=1, stable=True).indices)
    ordered = gather(bits, order)
    pos = torch.arange(order.shape[1], device=xyz.device).expand_as(order)
    starts = torch.ones_like(order, dtype=torch.bool)
    starts[:, 1:] = (ordered[:, 1:] != ordered[:, :-1]).any(-1)
    run_start = torch.where(starts, pos, torch.zeros_like(pos)).cummax(dim=1).values
    return torch.empty_like(order).scatter_(1, order, order.gather(1, run_start))


def first_copy_or_none(xyz: torch.Tensor) -> torch.Tensor | None:
    """:func:`first_copy` of ``xyz (B, N, 3)``, or ``None`` when it has no copies (the
    backbones' paths that evaluate each distinct point once then have nothing to skip)."""
    first = first_copy(xyz)
    if bool((first == torch.arange(xyz.shape[1], device=xyz.device)).all()):
        return None
    return first


def unique_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``x (N, C)`` in lexicographic order ``(U, C)`` and the index of each
    row among them ``(N,)`` int64: ``torch.unique(x, dim=0, return_inverse=True)``, the same
    values, by ``C`` stable sorts of one column each (torch's ``unique_dim`` compares rows one
    pair at a time on CPU: 3 ms for 2,048 rows against 0.3 ms).
    """
    n, c = x.shape
    order = torch.sort(x[:, c - 1], stable=True).indices
    for col in range(c - 2, -1, -1):  # least significant column first: lexicographic
        key = x[:, col].index_select(0, order)
        order = order.index_select(0, torch.sort(key, stable=True).indices)
    rows = x.index_select(0, order)
    new = torch.ones(n, dtype=torch.bool, device=x.device)
    new[1:] = (rows[1:] != rows[:-1]).any(1)
    inverse = torch.empty_like(order).scatter_(0, order, new.cumsum(0) - 1)
    return rows[new], inverse


def farthest_point_sample(xyz: torch.Tensor, n: int, start: int = 0) -> torch.Tensor:
    """Farthest-point sampling as PointNet++: ``xyz (B, N, 3)`` -> ``(B, n)`` int64.

    Starts at index ``start`` of every row; each next point is the one farthest from those
    chosen (ties: the lowest index, as ``argmax``). The ``n`` iterations are sequential by
    nature: on CPU with numba installed (``pip install 'pointtrack[fast]'``) they run compiled
    (:func:`trackers.kernels.fps_kernel`, ~10-20x faster than a Python loop of torch ops at
    batch 1); otherwise (or on another device) as a loop vectorised over the batch and the
    points. Both compute the squared distances with the same float32 operations in the same
    order (``(dx^2 + dy^2) + dz^2``), so they pick the same indices.
    """
    b, npts, _ = xyz.shape
    if n > npts:
        raise ValueError(f"cannot sample {n} of {npts} points")
    kernel = kernels.fps_kernel() if kernels.compilable(xyz) else None
    if kernel is not None:
        out = torch.empty(b, n, dtype=torch.long)
        if n > 0:
            kernel(xyz.detach().contiguous().numpy(), n, start, out.numpy())
        return out
    picks = []
    mind = torch.full((b, npts), float("inf"), dtype=xyz.dtype, device=xyz.device)
    cur = torch.full((b,), start, dtype=torch.long, device=xyz.device)
    for _ in range(n):
        picks.append(cur)
        centre = torch.gather(xyz, 1, cur.view(b, 1, 1).expand(b, 1, xyz.shape[-1]))
        torch.minimum(mind, (xyz - centre).square_().sum(-1), out=mind)
        cur = mind.argmax(dim=1)
    return torch.stack(picks, dim=1) if picks else torch.empty(b, 0, dtype=torch.long)


def ball_query(
    radius: float, k: int, xyz: torch.Tensor, centres: torch.Tensor, return_count: bool = False
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """PointNet++ ball query: ``xyz (B, N, 3)``, ``centres (B, M, 3)`` -> ``idx (B, M, k)``.

    For each centre, the first ``k`` points (in index order) with distance ``< radius``; when
    fewer are found, the remaining slots repeat the first hit; no hit at all gives index 0 (as
    the CUDA kernel, whose output starts zeroed). With ``return_count`` also the number of real
    hits ``(B, M)`` capped at ``k`` (slots ``>= count`` are padding).

    Vectorised: hits keep their index as a key, misses get ``N``; the ``k`` smallest keys (a
    ``topk``, no sort over ``N``) are the first ``k`` hits in index order.
    """
    n = xyz.shape[1]
    with torch.no_grad():  # indices only: no graph through the distances
        inside = pairwise_sqdist(centres, xyz) < radius * radius  # (B, M, N)
    ar = torch.arange(n, dtype=torch.int32, device=xyz.device)
    key = torch.where(inside, ar, n)
    kk = min(k, n)
    first = key.topk(kk, dim=-1, largest=False, sorted=True).values.long()  # (B, M, kk)
    count = (first < n).sum(-1)  # (B, M)
    if kk < k:  # fewer points than k: pad the slot dimension
        first = torch.cat([first, first.new_full((*first.shape[:2], k - kk), n)], dim=-1)
    head = torch.where(count[..., None] > 0, first[..., :1], torch.zeros_like(first[..., :1]))
    idx = torch.where(first < n, first, head)
    if return_count:
        return idx, count
    return idx


def ball_query_pairs(
    radius: float,
    k: int,
    xyz: torch.Tensor,
    centres: torch.Tensor,
    keep_centres: torch.Tensor | None = None,
    keep_points: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The real hits of :func:`ball_query` as flat pairs: ``xyz (B, N, 3)``, ``centres (B, M, 3)``
    -> ``group (P,)`` (flat centre index ``b * M + m``) and ``point (P,)`` (flat point index
    ``b * N + j``), sorted by centre then point.

    Per centre the first ``k`` hits in index order - the slots of ``ball_query`` below its count;
    a centre without hits gets the one pair ``(centre, point 0)``, as its all-zero ``idx`` row.
    ``keep_centres (B, M)`` / ``keep_points (B, N)`` bool (default: all) leave out the pairs of
    the other centres and points, after the query: a hit left out still counts towards the
    ``k`` (the backbone keeps the first copies of repeated points this way, and the compiled
    scan skips the centres left out).
    On CPU with numba (the ``fast`` extra) a compiled scan that stops at each centre's ``k``-th
    hit (:func:`trackers.kernels.ball_kernel`). Otherwise small problems test every pair
    (:func:`_ball_dense`), larger ones only the points of the 3 x 3 grid cells around each
    centre (:func:`_ball_grid`), unless those are a large share of all pairs (clustered
    clouds). The hit test is the same distance formula on every path, so the pairs are the
    same.
    """
    with torch.no_grad():  # indices only: no graph through the distances
        b, n = xyz.shape[:2]
        m = centres.shape[1]
        kernel = kernels.ball_kernel() if kernels.compilable(xyz, centres) else None
        if kernel is not None and k > 0:
            points = xyz.detach().contiguous().numpy()
            r2 = points.dtype.type(radius * radius)  # the tensor's dtype, as torch's comparison
            keeps = [  # (0, 0): keep all
                _KEEP_ALL if keep is None else keep.contiguous().numpy()
                for keep in (keep_centres, keep_points)
            ]
            group, point = kernel(points, centres.detach().contiguous().numpy(), r2, k, *keeps)
            return torch.from_numpy(group), torch.from_numpy(point)
        if b * m * n <= _DENSE_PAIRS:
            group, point = _ball_dense(radius, k, xyz, centres)
        else:
            group, point = _ball_grid(radius, k, xyz, centres)
        point = point + torch.div(group, m, rounding_mode="floor") * n
        if keep_centres is None and keep_points is None:
            return group, point
        keep = torch.ones_like(group, dtype=torch.bool)
        if keep_centres is not None:
            keep &= keep_centres.flatten()[group]
        if keep_points is not None:
            keep &= keep_points.flatten()[point]
        return group[keep], point[keep]


#: The compiled ball query's mask for "keep every centre / point" (never written; writable as
#: the masks from tensors are, so that numba compiles one signature).
_KEEP_ALL = np.zeros((0, 0), np.bool_)
#: :func:`ball_query_pairs` tests every pair up to this many (``B * M * N``), else grid cells.
_DENSE_PAIRS = 1 << 18
#: ... unless the grid's candidates are more than ``1 / _GRID_SHARE`` of the pairs: a candidate
#: costs ~10x a pair of the dense test (env search crops: 10-25 % of the pairs, where the grid
#: took 1.6x the dense time; uniform toy clouds: ~2 %, where it took 0.4x).
_GRID_SHARE = 10


def _ball_dense(
    radius: float, k: int, xyz: torch.Tensor, centres: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every point a candidate -> flat centre index ``(P,)``, point index in its row ``(P,)``.

    A running hit count (``cumsum``) marks the first ``k`` hits, one ``nonzero`` lists them.
    """
    n = xyz.shape[1]
    inside = pairwise_sqdist(centres, xyz) < radius * radius  # (B, M, N)
    # int16 (several times faster than int32 on CPU) where the count cannot wrap
    rank = inside.cumsum(dim=-1, dtype=torch.int16 if n < 2**15 else torch.int32)
    keep = inside & (rank <= k)
    keep[..., 0] |= rank[..., -1] == 0
    pairs = keep.view(-1, n).nonzero()  # (P, 2): flat centre, point within its row
    return pairs[:, 0], pairs[:, 1]


def _ball_grid(
    radius: float, k: int, xyz: torch.Tensor, centres: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidates from the 3 x 3 cells of an ``x, y`` grid around each centre -> flat centre
    index ``(P,)``, point index in its row ``(P,)``.

    Cells are a little wider than ``radius`` and indexed in float64, so every hit (even one the
    float32 test admits by rounding) lies in a neighbouring cell. Points sorted by
    ``(batch, x cell, y cell)`` make each neighbouring column of three cells one contiguous
    range; the hits among the candidates are sorted by ``(centre, point)`` and the first ``k``
    per centre kept.
    """
    b, n = xyz.shape[:2]
    m = centres.shape[1]
    dev = xyz.device
    cell = radius * (1 + 1e-4) + 1e-6
    ij = torch.floor(torch.cat([xyz[..., :2], centres[..., :2]], 1).double() / cell).long()
    ij = ij - ij.flatten(0, 1).amin(0) + 1  # >= 1: a neighbour cell index is never negative
    nx, ny = (int(v) + 2 for v in ij.flatten(0, 1).amax(0))
    key = (torch.arange(b, device=dev)[:, None] * nx + ij[..., 0]) * ny + ij[..., 1]  # (B, N+M)
    sorted_key, by_key = key[:, :n].flatten().sort(stable=True)  # by_key: flat point index
    first_cell = key[:, n:].flatten()[:, None] + torch.tensor([-ny - 1, -1, ny - 1], device=dev)
    lo = torch.searchsorted(sorted_key, first_cell)  # (B*M, 3): one column of 3 cells each
    count = (torch.searchsorted(sorted_key, first_cell + 2, right=True) - lo).flatten()
    total = int(count.sum())
    if total * _GRID_SHARE > b * m * n:  # dense clouds (the env's crops): testing every pair
        return _ball_dense(radius, k, xyz, centres)  # is cheaper than the candidates' ops
    column = torch.repeat_interleave(torch.arange(b * m * 3, device=dev), count, output_size=total)
    offset = torch.arange(total, device=dev) - (count.cumsum(0) - count).index_select(0, column)
    point = by_key.index_select(0, lo.flatten().index_select(0, column) + offset)
    group = torch.div(column, 3, rounding_mode="floor")
    p = xyz.reshape(-1, 3).index_select(0, point).t()
    c = centres.reshape(-1, 3).index_select(0, group).t()
    d = c[0] - p[0]  # the ops of pairwise_sqdist: the same rounding
    sq = d * d
    for axis in (1, 2):
        torch.sub(c[axis], p[axis], out=d)
        sq.add_(d.mul_(d))
    hit = sq < radius * radius
    group = group[hit]
    point = point[hit] - torch.div(group, m, rounding_mode="floor") * n  # index in its row
    hits = torch.bincount(group, minlength=b * m)
    if bool((hits == 0).any()):  # no hit: the pair (centre, point 0)
        empty = (hits == 0).nonzero().flatten()
        group = torch.cat([group, empty])
        point = torch.cat([point, torch.zeros_like(empty)])
        hits = hits.clamp(min=1)
    order = (group * n + point).sort().indices
    group, point = group.index_select(0, order), point.index_select(0, order)
    rank = torch.arange(len(group), device=dev) - (hits.cumsum(0) - hits).index_select(0, group)
    keep = rank < k
    return group[keep], point[keep]


def knn(k: int, query: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest neighbours in any dimension: ``query (B, M, C)``, ``ref (B, N, C)`` ->
    ``(sqdist (B, M, k), idx (B, M, k))`` sorted by increasing distance (ties: lower index
    first). Works for coordinates (C = 3) and feature spaces alike.
    """
    if k > ref.shape[1]:
        raise ValueError(f"k = {k} exceeds the {ref.shape[1]} reference points")
    kernel = kernels.knn_kernel() if kernels.compilable(query, ref) else None
    if kernel is not None and k > 0:
        b, m = query.shape[:2]
        sd = torch.empty(b, m, k, dtype=query.dtype)
        si = torch.empty(b, m, k, dtype=torch.long)
        q, r = query.detach().contiguous().numpy(), ref.detach().contiguous().numpy()
        kernel(q, r, sd.numpy(), si.numpy())
        if torch.is_grad_enabled() and (query.requires_grad or ref.requires_grad):
            # differentiable: the k chosen distances again, in pairwise_sqdist's order (same bits)
            d = query[:, :, None, :] - gather(ref, si)  # (B, M, k, 3)
            sd = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
        return sd, si
    d = pairwise_sqdist(query, ref)
    # a stable sort gives the documented tie order; topk's tie order is unspecified
    sd, si = torch.sort(d, dim=-1, stable=True)
    return sd[..., :k], si[..., :k]


def chamfer_distance(
    a: torch.Tensor, a_mask: torch.Tensor, b: torch.Tensor, b_mask: torch.Tensor
) -> torch.Tensor:
    """Symmetric Chamfer distance (the units of the points) between the masked point sets
    ``a (B, N, 3)`` / ``a_mask (B, N)`` and ``b (B, M, 3)`` / ``b_mask (B, M)`` (bool) -> ``(B,)``:
    the mean over ``a``'s points of the distance to the nearest point of ``b``, and the same
    from ``b`` to ``a``, averaged (a repeated point counts in its set's mean as often as it
    appears). ``inf`` where a set is empty. Symmetric bit for bit.

    One row at a time, from :func:`distinct_points` (copies compared once),
    :func:`nearest_distances` and :func:`layout_mean`: a row's value is bit for bit the same
    whatever else is in the batch.
    """
    out = []
    for i in range(a.shape[0]):
        pa, ia = distinct_points(a[i], a_mask[i])
        pb, ib = distinct_points(b[i], b_mask[i])
        if not (len(pa) and len(pb)):
            out.append(torch.full((1,), math.inf, dtype=a.dtype, device=a.device))
            continue
        a_near, b_near = nearest_distances(pa[None], None, pb)
        a_to_b = layout_mean(a_near, ia, a_mask[i : i + 1])
        out.append(0.5 * (a_to_b + layout_mean(b_near, ib, b_mask[i : i + 1])))
    return torch.cat(out) if out else a.new_zeros(0)


def distinct_points(points: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct masked points of one cloud ``points (L, 3)`` / ``mask (L,)`` (float32 copies
    bit for bit equal; the env's resampling repeats points many times) -> ``(U, 3)`` and the
    layout ``(L,)`` int64: the row of each masked point's copy (``U`` for the others). One sort
    by the (x, y) bits; copies a point of other z separates count twice, which is exact too.
    (The decision step's compiled path computes the same sets in
    :func:`trackers.kernels.scene_kernel`.)"""
    bits = points.contiguous().view(torch.int32)
    key = (bits[:, 0].long() << 32) | (bits[:, 1].long() & _MASK32)
    key = torch.where(mask, key, torch.iinfo(torch.int64).max)  # finite points sort first
    order = torch.argsort(key)
    ordered = bits.index_select(0, order)
    masked = mask.index_select(0, order)
    new = torch.ones_like(mask)
    new[1:] = (ordered[1:] != ordered[:-1]).any(1)
    new &= masked
    row = new.cumsum(0) - 1
    layout = torch.empty_like(order).scatter_(0, order, torch.where(masked, row, len(mask)))
    unique = points.index_select(0, order[new])
    return unique, torch.where(mask, layout, len(unique))


def nearest_distances(
    a: torch.Tensor, a_in: torch.Tensor | None, b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest-point distances between ``K`` sets of points ``a (K, U, 3)`` (``a_in (K, U)``
    bool: which points each set holds; ``None``: all) and the set ``b (V, 3)``: ``(K, U)`` from
    each of ``a``'s points to ``b`` and ``(K, V)`` from ``b``'s points to each set (``inf``
    for an empty set). One pairwise pass; exact to float rounding, the same on any device (and
    compiled, :func:`trackers.kernels.nearest_kernel`, with the same bits)."""
    k, u, c = a.shape
    kernel = kernels.nearest_kernel() if kernels.compilable(a, b) else None
    grad = torch.is_grad_enabled() and (a.requires_grad or b.requires_grad)
    if kernel is not None and not grad and u and len(b):
        a_near, b_near = a.new_empty(k, u), a.new_empty(k, len(b))
        inside = torch.ones(k, u, dtype=torch.bool) if a_in is None else a_in.contiguous()
        kernel(
            a.contiguous().numpy(),
            inside.numpy(),
            b.contiguous().numpy(),
            a_near.numpy(),
            b_near.numpy(),
        )
        return a_near.sqrt_(), b_near.sqrt_()
    sq = pairwise_sqdist(a.reshape(1, k * u, c), b[None]).reshape(k, u, -1)  # (K, U, V)
    if a_in is not None:  # a penalty of 0 / inf: exact (x + 0 = x)
        sq.add_(torch.where(a_in, 0.0, math.inf).to(sq.dtype)[..., None])
    return sq.amin(dim=2).sqrt(), sq.amin(dim=1).sqrt()


def layout_mean(near: torch.Tensor, layout: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The mean over a layout's masked positions ``mask (K, L)`` of their points' distances
    ``near (K, U)`` (``layout (L,)``: each position's point, :func:`distinct_points`) -> ``(K,)``.
    The sum runs over the whole ``(L,)`` layout, zeros at the unmasked positions, so it does
    not depend on how the points were deduplicated or batched."""
    full = near.gather(1, layout.clamp(max=near.shape[1] - 1).expand(near.shape[0], -1))
    return torch.where(mask, full, 0.0).sum(1) / mask.sum(1)


def load_kernels() -> bool:
    """Load every compiled kernel of these ops for float32 points now (numba's start and its disk
    cache: ~0.5 s of CPU), e.g. in a parent before it forks workers, which inherit them instead
    of each loading them again. ``False`` without numba (nothing to load)."""
    if kernels.hash_kernel() is None:
        return False
    points = torch.zeros(1, 4, 3)
    points[0, :, 0] = torch.arange(4.0)
    hash_orders([points], [0])
    farthest_point_sample(points, 2)
    ball_query_pairs(1.5, 2, points, points[:, :2])
    knn(2, points[:, :2], points)
    nearest_distances(points[:, :2], None, points[0])
    return True
