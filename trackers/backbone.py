"""PointNet++ backbone of P2B / BAT / GPT: three set-abstraction (SA) layers, then a ``1x1`` conv.

Reference constants (P2B, Qi et al. 2020; Open3DSOT): radii 0.3 / 0.5 / 0.7 m, 32 neighbours,
MLPs ``[3, 64, 64, 128]``, ``[128+3, 128, 128, 256]``, ``[256+3, 256, 256, 256]``, relative
(un-normalised) neighbour coordinates, max pooling, the number of points halved at each layer by
random sampling, and a final ``Conv1d(256, 256)``: 512 template points -> 64 seeds, 1024 search
points -> 128 seeds, 256-d features.

Sampling: the caller passes an ``order (B, N)`` of the input points (a random permutation in
training, :func:`trackers.ops.hash_order` in eval); layer ``i`` keeps the first ``N / 2**i``
points of that order - P2B's "random sampling" (which takes a prefix of a randomly resampled
cloud), with the order made explicit. ``sampling="fps"`` (Open3DSOT's BAT option) instead puts
the first layer's farthest-point sample (started at the first point of ``order``) in front.

Speed: the first Linear of each SA MLP acts on ``[p_j - c_i; f_j]``, which is linear, so it is
computed once per point (``W_x p_j + W_f f_j + b``) and once per centre (``W_x c_i``) and the
grouped pre-activation is ``gather - centre`` - the same function with ``k x`` fewer
multiplications. In eval mode groups are evaluated ragged: the padding slots of a ball query repeat
the first hit, whose features cannot change a max, so only the real hits go through the MLP (same
result; training keeps the dense layout so BatchNorm statistics match the reference, unless
``ragged_train=True``). Padded clouds (the env repeats the points of small clouds) are evaluated
once per distinct point in eval: copies of a centre share its features, copies of a neighbour
its MLP value (:meth:`SetAbstraction._distinct`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from trackers import ops
from trackers.layers import MLP, grouped_max

__all__ = ["Backbone", "BackboneConfig", "SetAbstraction"]


@dataclass
class BackboneConfig:
    """Backbone hyper-parameters (defaults: the papers')."""

    radii: tuple[float, ...] = (0.3, 0.5, 0.7)
    neighbours: int = 32
    channels: tuple[tuple[int, ...], ...] = ((64, 64, 128), (128, 128, 256), (256, 256, 256))
    out_channels: int = 256
    ragged_eval: bool = True
    # ragged in training too: BatchNorm statistics over the real hits only (the reference counts
    # the padding copies); several times less backbone work, so CPU training is ~2x faster
    ragged_train: bool = False
    sampling: str = "random"  # or "fps": farthest-point sampling at the first layer (BAT's option)

    def __post_init__(self) -> None:
        self.radii = tuple(float(r) for r in self.radii)
        self.channels = tuple(tuple(int(c) for c in layer) for layer in self.channels)
        if len(self.radii) != len(self.channels):
            raise ValueError(
                f"backbone: {len(self.radii)} radii but {len(self.channels)} channel lists"
            )
        if self.sampling not in ("random", "fps"):
            raise ValueError(f"backbone: sampling must be 'random' or 'fps', got {self.sampling!r}")
        if self.neighbours < 1 or any(r <= 0 for r in self.radii):
            raise ValueError("backbone: neighbours and radii must be positive")


class SetAbstraction(nn.Module):
    """One SA layer: ``xyz (B, N, 3)``, ``feats (B, N, C) | None`` -> ``(B, n, 3), (B, n, C')``.

    Centres are the first ``n`` points; neighbours by :func:`trackers.ops.ball_query`.
    """

    def __init__(self, in_channels: int, channels: tuple[int, ...], radius: float, k: int,
                 ragged_eval: bool = True, ragged_train: bool = False) -> None:
        super().__init__()
        self.radius, self.k = radius, k
        self.ragged_eval, self.ragged_train = ragged_eval, ragged_train
        self.in_channels = in_channels
        self.mlp = MLP([in_channels + 3, *channels])

    def point_terms(self, xyz: torch.Tensor, feats: torch.Tensor | None,
                    centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """First-layer parts: per point ``(B, N, C1)`` and per centre ``(B, n, C1)``."""
        w, b = self.mlp.linear_params(0)
        wx = w[:, :3]
        inp = xyz if feats is None else torch.cat([xyz, feats], dim=-1)
        per_point = torch.nn.functional.linear(inp, w, b)
        per_centre = centres @ wx.t()
        return per_point, per_centre

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor | None, n: int,
                first: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``first (B, N)``: :func:`trackers.ops.first_copy` of ``xyz`` (ragged path only), to
        evaluate each distinct centre and neighbour once."""
        centres = xyz[:, :n]
        per_point, per_centre = self.point_terms(xyz, feats, centres)
        if self.ragged_train if self.training else self.ragged_eval:
            group, point = ops.ball_query_pairs(self.radius, self.k, xyz, centres)
            if first is None:
                return centres, grouped_max(self.mlp, per_point, per_centre, group, point)
            return centres, self._distinct(per_point, per_centre, group, point, first)
        idx = ops.ball_query(self.radius, self.k, xyz, centres)
        pre = ops.group(per_point, idx) - per_centre[:, :, None, :]  # (B, n, k, C1)
        return centres, self.mlp.forward_from(0, pre).amax(dim=2)

    def _distinct(self, per_point: torch.Tensor, per_centre: torch.Tensor, group: torch.Tensor,
                  point: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
        """:func:`grouped_max` over first copies only, then copied to the other copies.

        Copies of a point have equal coordinates and (same ball, same hits) equal features, so
        a copy of a centre has the same group and a copy of a hit the same MLP input; the first
        copy of a hit is itself a hit, earlier in index order, so it is among the kept slots.
        """
        b, n = per_centre.shape[:2]
        npts = per_point.shape[1]
        own = first == torch.arange(npts, device=first.device)  # (B, N): first copies
        keep = own.flatten()[point] & own[:, :n].flatten()[group]
        out = grouped_max(self.mlp, per_point, per_centre, group[keep], point[keep])
        src = first[:, :n] + (torch.arange(b, device=first.device) * n)[:, None]
        return out.flatten(0, 1).index_select(0, src.flatten()).view(b, n, -1)


class Backbone(nn.Module):
    """``points (B, N, 3)``, ``order (B, N)`` -> seeds ``xyz (B, N/8, 3)``, ``feats (B, N/8, D)``,
    ``idx (B, N/8)`` (indices of the seeds in ``points``).
    """

    def __init__(self, config: BackboneConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or BackboneConfig()
        layers, c_in = [], 0
        for radius, chans in zip(config.radii, config.channels, strict=True):
            layers.append(
                SetAbstraction(c_in, chans, radius, config.neighbours, config.ragged_eval,
                               config.ragged_train))
            c_in = chans[-1]
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(c_in, config.out_channels)

    @property
    def out_channels(self) -> int:
        return self.config.out_channels

    def forward(self, points: torch.Tensor, order: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if self.config.sampling == "fps":  # FPS picks first (in FPS order), then the rest
            first = ops.farthest_point_sample(ops.gather(points, order), points.shape[1] // 2)
            rest = torch.ones_like(order, dtype=torch.bool).scatter_(1, first, False)
            pos = torch.arange(order.shape[1], device=order.device).expand_as(order)
            rest_idx = pos[rest].view(order.shape[0], -1)
            order = torch.gather(order, 1, torch.cat([first, rest_idx], dim=1))
        xyz = ops.gather(points, order)
        feats = None
        first = None
        if not self.training and all(layer.ragged_eval for layer in self.layers):
            first = ops.first_copy(xyz)
            if bool((first == torch.arange(xyz.shape[1], device=xyz.device)).all()):
                first = None  # no copies: nothing to skip
        n = points.shape[1]
        for layer in self.layers:
            n //= 2
            # layer inputs are prefixes of xyz and a first copy precedes its copies
            xyz, feats = layer(xyz, feats, n, None if first is None else first[:, :xyz.shape[1]])
        return xyz, self.out(feats), order[:, :n]
