"""MBPTrack's building blocks (Xu et al., "MBPTrack: Improving 3D Point Cloud Tracking with
Memory Networks and Box Priors", ICCV 2023): the DGCNN-style backbone, the memory transformer
layer that propagates target features and per-point target masks, and the box-prior
localisation network (BPLocNet). Facts (widths, sampling, losses) follow the authors' code
(``slothfulxtx/MBPTrack3D``: ``models/MBPTrack/{backbone,transformer,rpn}.py``); the code here is
our own, pure torch, on points as rows ``(B, N, C)``.

Every "conv1d with BatchNorm" of the reference is a :class:`trackers.layers.MLP` layer (Linear ->
BatchNorm -> ReLU), every plain conv1d the MLP's last, bias-carrying Linear.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from trackers import ops
from trackers.layers import MLP, dense_max

__all__ = ["BPLocNet", "DGCNNBackbone", "MemoryTransformerLayer", "box_prior_offsets", "knn_idx"]


def knn_idx(k: int, query: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Indices ``(B, M, k)`` of the ``k`` nearest points of ``ref (B, N, 3)`` to each of ``query
    (B, M, 3)`` (:func:`trackers.ops.knn`: ties to the lower index; ``k`` capped at ``N``)."""
    with torch.no_grad():  # indices only
        return ops.knn(min(k, ref.shape[1]), query, ref)[1]


def _first_layer_split(
    mlp: MLP, per_point_in: torch.Tensor, per_centre_in: torch.Tensor, split: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The first Linear of ``mlp`` on edges ``[a_j - a_i, a_i]`` (``a``: ``split`` channels)
    written as ``W_1 a_j + (W_2 - W_1) a_i + b``: -> (per point ``(B, N, H)``, per centre ``(B,
    M, H)``); the edge's pre-activation is their sum (exact algebra, far fewer products)."""
    w, b = mlp.linear_params(0)
    w_diff, w_centre = w[:, :split], w[:, split:]
    return F.linear(per_point_in, w_diff), F.linear(per_centre_in, w_centre - w_diff, b)


def _edge_sum(grouped: torch.Tensor, per_centre: torch.Tensor) -> torch.Tensor:
    """``grouped (B, M, k, H) + per_centre (B, M, 1, H)``, into ``grouped`` (a fresh gather)
    where no gradient is recorded: the same sums without writing a second ``(B, M, k, H)``."""
    if torch.is_grad_enabled() and (grouped.requires_grad or per_centre.requires_grad):
        return grouped + per_centre
    return grouped.add_(per_centre)


class EdgeConv(nn.Module):
    """One DGCNN EdgeConv layer with range sampling: the first ``n`` points are the centres (the
    caller orders the cloud randomly or by hash, so a prefix is a random sample); each centre's
    ``k`` nearest points (xyz) give edges ``[f_j - f_i, f_i]`` with ``f = [features, xyz]``,
    through a shared MLP, max-pooled over the neighbours."""

    def __init__(self, in_channels: int, channels: list[int], k: int) -> None:
        super().__init__()
        self.k = int(k)
        self.mlp = MLP([2 * (in_channels + 3), *channels])

    def forward(
        self,
        xyz: torch.Tensor,
        feat: torch.Tensor | None,
        n: int,
        first: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``xyz (B, N, 3)``, ``feat (B, N, C)`` or ``None`` -> centres ``(B, n, 3)`` and their
        features ``(B, n, C')``. ``first (1, N)`` (one cloud: :func:`trackers.ops.first_copy`
        of ``xyz``): only the first copy of each centre is evaluated and its copies take its
        features: copies have the same coordinates and features, so the same neighbours (the
        kNN breaks ties by index among all points) and the same edges."""
        f = xyz if feat is None else torch.cat([feat, xyz], dim=-1)
        centres = xyz[:, :n]
        if first is None:
            own = slice(None, n)
        else:  # the first copies among the centres (a first copy precedes its copies)
            first = first[0, :n]
            own_mask = first == torch.arange(n, device=first.device)
            own = own_mask.nonzero()[:, 0]
        idx = knn_idx(self.k, centres[:, own], xyz)  # (B, n or R, k)
        per_point, per_centre = _first_layer_split(self.mlp, f, f[:, own], f.shape[-1])
        pre = _edge_sum(ops.group(per_point, idx), per_centre[:, :, None])
        out = dense_max(self.mlp, pre, 2, torch.amax)
        if first is not None:  # each centre's row: its first copy's among the evaluated
            out = out.index_select(1, (own_mask.cumsum(0) - 1)[first])
        return centres, out


class DGCNNBackbone(nn.Module):
    """Three EdgeConv layers keeping ``N / r`` points for the ratios ``r`` (2, 4, 8), then a
    Linear to ``out_channels``: ``(B, N, 3)`` (ordered) -> seeds ``xyz (B, N / 8, 3)``, ``feat (B,
    N / 8, D)``; the seeds are the cloud's first ``N / 8`` points."""

    def __init__(
        self, channels: list[list[int]], k: int, ratios: list[int], out_channels: int
    ) -> None:
        super().__init__()
        c_in = [0] + [c[-1] for c in channels[:-1]]
        self.layers = nn.ModuleList(EdgeConv(i, c, k) for i, c in zip(c_in, channels, strict=True))
        self.ratios = [int(r) for r in ratios]
        self.fc = nn.Linear(channels[-1][-1], out_channels)

    @property
    def out_channels(self) -> int:
        """The seed feature width ``D``."""
        return self.fc.out_features

    def forward(self, xyz: torch.Tensor, copies: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``copies=True`` (one cloud, eval: the env repeats points to fill a crop, and on its
        search regions most centres are copies): each distinct centre evaluated once
        (:class:`EdgeConv`'s ``first``); the same values to float rounding."""
        n = xyz.shape[1]
        first = ops.first_copy_or_none(xyz) if copies and xyz.shape[0] == 1 else None
        feat = None
        for layer, ratio in zip(self.layers, self.ratios, strict=True):
            prefix = None if first is None else first[:, : xyz.shape[1]]  # layer inputs: prefixes
            xyz, feat = layer(xyz, feat, max(1, n // ratio), prefix)
        return xyz, self.fc(feat)


class SharedAttention(nn.Module):
    """Attention whose weights (from shared query / key projections) average two value streams,
    each with its own value and output projection (the reference's ``SharedMultiheadAttention``:
    features and mask embeddings move together). No projection biases but the outputs'."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"feat_dim {dim} is not divisible by heads {heads}")
        self.heads, self.dropout = heads, float(dropout)
        self.q = nn.Linear(dim, dim, bias=False)
        self.k = nn.Linear(dim, dim, bias=False)
        self.v = nn.Linear(dim, dim, bias=False)
        self.v2 = nn.Linear(dim, dim, bias=False)
        self.out = nn.Linear(dim, dim)
        self.out2 = nn.Linear(dim, dim)

    def _split(self, x: torch.Tensor) -> torch.Tensor:  # (B, N, D) -> (B, h, N, D / h)
        return x.unflatten(-1, (self.heads, -1)).transpose(1, 2)

    def forward(
        self,
        query: torch.Tensor,
        key: torch.Tensor,
        value: torch.Tensor,
        value2: torch.Tensor,
        key_valid: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``query (B, N, D)``, ``key`` / ``value`` / ``value2 (B, L, D)``, ``key_valid (B, L)``
        bool (at least one True per row) -> two ``(B, N, D)``."""
        q, k = self._split(self.q(query)), self._split(self.k(key))
        logits = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])  # (B, h, N, L)
        if key_valid is not None and not bool(key_valid.all()):  # a full memory masks nothing
            logits = logits.masked_fill(~key_valid[:, None, None, :], -math.inf)
        attn = F.dropout(logits.softmax(dim=-1), self.dropout, self.training)
        outs = []
        for proj, out in ((self.v, self.out), (self.v2, self.out2)):
            mixed = (attn @ self._split(proj(value if proj is self.v else value2))).transpose(1, 2)
            outs.append(out(mixed.flatten(2)))
        return outs[0], outs[1]


class MemoryTransformerLayer(nn.Module):
    """One layer of the memory transformer: cross-attention from the current frame's seeds to the
    memory (keys: memory features + their position embeddings; values: the features, and the
    embedded per-point target masks), self-attention, feed-forward; the feature and mask streams
    share the attention weights and keep separate norms and feed-forward nets (pre-norm,
    residual). ``memory_features`` is what a frame contributes to later frames' memory at this
    layer (the reference's ``mem_ffn``: BatchNorm, ReLU, Linear-BN-ReLU, Linear)."""

    def __init__(self, dim: int, heads: int, ffn: int, dropout: float) -> None:
        super().__init__()
        self.cross = SharedAttention(dim, heads, dropout)
        self.self_attn = SharedAttention(dim, heads, dropout)
        self.mem_norm_in = nn.BatchNorm1d(dim)
        self.mem_ffn = MLP([dim, dim, dim], last_activation=False)
        self.mask_emb = nn.Linear(1, dim)
        self.norms = nn.ModuleDict(
            {n: nn.LayerNorm(dim) for n in ("x1", "m1", "x2", "m2", "mem", "ffn", "ffn_m")}
        )
        self.pos_q = MLP([3, dim, dim], last_activation=False)
        self.pos_m = MLP([3, dim, dim], last_activation=False)
        self.pos = MLP([3, dim, dim], last_activation=False)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn), nn.ReLU(), nn.Linear(ffn, dim))
        self.ffn_m = nn.Sequential(nn.Linear(dim, ffn), nn.ReLU(), nn.Linear(ffn, dim))
        self.p = float(dropout)

    def memory_features(self, feat: torch.Tensor) -> torch.Tensor:
        """``(B, N, D)`` -> ``(B, N, D)``: a frame's features as memory keys / values."""
        shape = feat.shape
        x = F.relu(self.mem_norm_in(feat.reshape(-1, shape[-1]))).reshape(shape)
        return self.mem_ffn(x)

    def initial_mask(self, feat: torch.Tensor) -> torch.Tensor:
        """The current frame's mask embedding before any layer: mask 0.5 (unknown)."""
        return self.mask_emb(feat.new_full((*feat.shape[:2], 1), 0.5))

    def forward(
        self,
        x: torch.Tensor,
        mask_x: torch.Tensor,
        xyz: torch.Tensor,
        mem: torch.Tensor,
        mem_xyz: torch.Tensor,
        mem_mask: torch.Tensor,
        mem_valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Seeds ``x``, ``mask_x (B, N, D)`` at ``xyz (B, N, 3)``; memory ``mem (B, L, D)`` at
        ``mem_xyz (B, L, 3)`` (the current frame's coordinates) with masks ``mem_mask (B, L)`` in
        [0, 1] and ``mem_valid (B, L)`` bool -> the updated ``x``, ``mask_x``."""
        n = self.norms
        mem_norm = n["mem"](mem)
        v2 = n["m2"](self.mask_emb(mem_mask[..., None]))
        q = n["x2"](x) + self.pos_q(xyz)
        xx, mm = self.cross(q, mem_norm + self.pos_m(mem_xyz), mem_norm, v2, mem_valid)
        x = x + F.dropout(xx, self.p, self.training)
        mask_x = mask_x + F.dropout(mm, self.p, self.training)
        xn, mn = n["x1"](x), n["m1"](mask_x)
        qk = xn + self.pos(xyz)
        xx, mm = self.self_attn(qk, qk, xn, mn)
        x = x + F.dropout(xx, self.p, self.training)
        mask_x = mask_x + F.dropout(mm, self.p, self.training)
        x = x + F.dropout(self.ffn(n["ffn"](x)), self.p, self.training)
        mask_x = mask_x + F.dropout(self.ffn_m(n["ffn_m"](mask_x)), self.p, self.training)
        return x, mask_x


def box_prior_offsets(nx: int, ny: int, nz: int) -> torch.Tensor:
    """The box-prior sample grid ``(nx ny nz, 3)`` in units of the box size: cell centres of an
    ``nx x ny x nz`` split of the unit box, centred (the reference's ``shrink`` sampling)."""
    axes = [(np.arange(n) + 0.5) / n - 0.5 for n in (nx, ny, nz)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return torch.tensor(grid, dtype=torch.float32)


class BPLocNet(nn.Module):
    """Box-prior localisation: per-seed target mask and coarse centre (with a coarse objectness),
    farthest-point sampling of ``proposals`` centres, box-prior sampling (the ``3 x 3 x 5`` grid
    of :func:`box_prior_offsets` scaled by the target's size around each centre), point-to-
    reference feature aggregation (each grid point's ``k`` nearest seeds, edges ``[x_j - g, g,
    f_j]``, shared MLP, max), one feature per proposal from its grid points' features and its
    coarse objectness, and a head to the refined ``(dx, dy, dz, yaw in degrees, score)``."""

    def __init__(self, dim: int, grid: list[int], proposals: int, k: int) -> None:
        super().__init__()
        self.proposals, self.k = int(proposals), int(k)
        self.register_buffer("grid", box_prior_offsets(*grid), persistent=False)
        s = self.grid.shape[0]
        self.fc_mask = MLP([dim, dim, dim, 1], last_activation=False)
        self.fc_center = MLP([dim + 3, dim, dim, 3 + 1 + dim], last_activation=False)
        self.pre = MLP([dim + 1, dim, dim], last_activation=False)
        self.edge = MLP([dim + 6, dim, dim, dim])
        self.aggr = MLP([s * dim, dim])
        self.center_emb = nn.Linear(1, dim)
        self.fc_proposal = MLP([dim, dim, dim, 5], last_activation=False)

    def forward(
        self, xyz: torch.Tensor, feat: torch.Tensor, mask_feat: torch.Tensor, lwh: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Seeds ``xyz (B, N, 3)``, features ``feat``, ``mask_feat (B, N, D)``, target size
        ``lwh (B, 3)`` (m) -> ``mask_logits (B, N)``, ``center (B, N, 3)``, ``coarse_logits (B,
        N)``, ``proposal_xyz (B, K, 3)``, ``boxes (B, K, 5)`` (x, y, z in m, yaw in degrees,
        score logit), ``feature (B, N, D)``."""
        d = feat.shape[-1]
        feat = feat + mask_feat
        mask_logits = self.fc_mask(feat)[..., 0]
        offset_feat, offset, coarse = self.fc_center(torch.cat([feat, xyz], -1)).split(
            [d, 3, 1], dim=-1
        )
        feat = feat + offset_feat
        center = xyz + offset
        coarse = coarse[..., 0]
        k_prop = min(self.proposals, center.shape[1])
        fps = ops.farthest_point_sample(center.detach(), k_prop)  # (B, K)
        proposal_xyz = ops.gather(center, fps)
        score = ops.gather(coarse.sigmoid()[..., None], fps)  # (B, K, 1)
        b = xyz.shape[0]
        samples = proposal_xyz[:, :, None] + self.grid * lwh[:, None, None, :]  # (B, K, S, 3)
        samples = samples.reshape(b, -1, 3)
        feat_s = self.pre(torch.cat([mask_logits.sigmoid()[..., None], feat], -1))
        idx = knn_idx(self.k, samples, xyz)  # (B, K S, k)
        # edge [x_j - g, g, f_j]: the first Linear split into a per-seed and a per-sample part
        w, bias = self.edge.linear_params(0)
        per_seed = F.linear(xyz, w[:, :3]) + F.linear(feat_s, w[:, 6:])
        per_sample = F.linear(samples, w[:, 3:6] - w[:, :3], bias)
        pre = _edge_sum(ops.group(per_seed, idx), per_sample[:, :, None])
        sample_feat = dense_max(self.edge, pre, 2, torch.amax)  # (B, K S, D)
        proposal_feat = self.aggr(sample_feat.reshape(b, k_prop, -1))
        out = self.fc_proposal(proposal_feat + self.center_emb(score))
        boxes = torch.cat([out[..., :3] + proposal_xyz, out[..., 3:]], dim=-1)
        return {
            "mask_logits": mask_logits,
            "center": center,
            "coarse_logits": coarse,
            "proposal_xyz": proposal_xyz,
            "boxes": boxes,
            "feature": feat,
        }
