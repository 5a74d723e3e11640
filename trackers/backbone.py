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

The first Linear of each SA MLP acts on ``[p_j - c_i; f_j]``, which is linear, so it is computed
once per point (``W_x p_j + W_f f_j + b``) and once per centre (``W_x c_i``) and the grouped
pre-activation is ``gather - centre`` - the same function with ``k x`` fewer multiplications
(every path, training included).

Plain path (training, and eval with ``fast_eval=False``): dense ``(B, n, k)`` ball-query groups,
one cloud at a time. Fast eval path (``fast_eval=True``, the default; the same function up to
float rounding): groups are evaluated ragged - the padding slots of a ball query repeat the first
hit, whose features cannot change a max, so only the real hits go through the MLP; padded clouds
(the env repeats the points of small clouds) are evaluated once per distinct point - copies of a
centre share its features, copies of a neighbour its MLP value (:meth:`SetAbstraction.ragged`);
the template and the search region go through each layer together
(:meth:`Backbone.forward_many`): one MLP evaluation per layer. ``ragged_train=True`` uses the
ragged groups in training too (BatchNorm statistics over the real hits only: a different,
cheaper training computation, not an exact speed-up).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from trackers import ops
from trackers.layers import MLP, grouped_max, max_pool

__all__ = ["Backbone", "BackboneConfig", "SetAbstraction"]


@dataclass
class BackboneConfig:
    """Backbone hyper-parameters (defaults: the papers')."""

    radii: tuple[float, ...] = (0.3, 0.5, 0.7)
    neighbours: int = 32
    channels: tuple[tuple[int, ...], ...] = ((64, 64, 128), (128, 128, 256), (256, 256, 256))
    out_channels: int = 256
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

    def __init__(
        self,
        in_channels: int,
        channels: tuple[int, ...],
        radius: float,
        k: int,
        ragged_train: bool = False,
    ) -> None:
        super().__init__()
        self.radius, self.k = radius, k
        self.ragged_train = ragged_train
        self.fast_eval = True  # eval: ragged groups (see the module doc)
        self.mlp = MLP([in_channels + 3, *channels])

    def point_terms(
        self, xyz: torch.Tensor, feats: torch.Tensor | None, centres: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """First-layer parts: per point ``(B, N, C1)`` and per centre ``(B, n, C1)``."""
        w, b = self.mlp.linear_params(0)
        wx = w[:, :3]
        inp = xyz if feats is None else torch.cat([xyz, feats], dim=-1)
        per_point = torch.nn.functional.linear(inp, w, b)
        per_centre = centres @ wx.t()
        return per_point, per_centre

    def forward(
        self,
        xyz: torch.Tensor,
        feats: torch.Tensor | None,
        n: int,
        first: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``first (B, N)``: :func:`trackers.ops.first_copy` of ``xyz`` (ragged path only), to
        evaluate each distinct centre and neighbour once."""
        if self.ragged_train if self.training else self.fast_eval:
            return self.ragged([xyz], [feats], [n], [first])[0]
        centres = xyz[:, :n]
        per_point, per_centre = self.point_terms(xyz, feats, centres)
        idx = ops.ball_query(self.radius, self.k, xyz, centres)
        pre = ops.group(per_point, idx) - per_centre[:, :, None, :]  # (B, n, k, C1)
        return centres, max_pool(self.mlp.forward_from(0, pre, fresh=True), 2)

    def ragged(
        self,
        xyzs: list[torch.Tensor],
        feats: list[torch.Tensor | None],
        ns: list[int],
        firsts: list[torch.Tensor | None],
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The layer on several clouds ``(B, N_i, 3)`` (same ``B``, e.g. template and search) at
        once over the real ball-query hits only: one MLP evaluation for all their groups.

        With ``firsts[i]`` (:func:`trackers.ops.first_copy`) only first copies are evaluated:
        copies of a point have equal coordinates and (same ball, same hits) equal features, so
        a copy of a centre has the same group and a copy of a hit the same MLP input; the first
        copy of a hit is itself a hit, earlier in index order, so it is among the kept slots.
        """
        b = xyzs[0].shape[0]
        centres = [xyz[:, :n] for xyz, n in zip(xyzs, ns, strict=True)]
        terms = [
            self.point_terms(xyz, f, c) for xyz, f, c in zip(xyzs, feats, centres, strict=True)
        ]
        groups, points = [], []
        group_start = point_start = 0
        for xyz, c, first in zip(xyzs, centres, firsts, strict=True):
            own = None  # first copies only (of the centre and of the hit)
            if first is not None:
                own = first == torch.arange(xyz.shape[1], device=first.device)  # (B, N)
            group, point = ops.ball_query_pairs(
                self.radius, self.k, xyz, c, None if own is None else own[:, : c.shape[1]], own
            )
            groups.append(group + group_start)
            points.append(point + point_start)
            group_start += b * c.shape[1]
            point_start += b * xyz.shape[1]
        per_point = torch.cat([t[0].reshape(-1, t[0].shape[-1]) for t in terms])[None]
        per_centre = torch.cat([t[1].reshape(-1, t[1].shape[-1]) for t in terms])[None]
        out = grouped_max(self.mlp, per_point, per_centre, torch.cat(groups), torch.cat(points))
        results, start = [], 0
        for c, first in zip(centres, firsts, strict=True):
            n = c.shape[1]
            rows = out[0, start : start + b * n]
            if first is not None:  # copies of a centre take their first copy's features
                src = first[:, :n] + (torch.arange(b, device=first.device) * n)[:, None]
                rows = rows.index_select(0, src.flatten())
            results.append((c, rows.view(b, n, -1)))
            start += b * n
        return results


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
                SetAbstraction(c_in, chans, radius, config.neighbours, config.ragged_train)
            )
            c_in = chans[-1]
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(c_in, config.out_channels)
        self.fast_eval = True  # eval: all clouds through each layer together, ragged groups

    @property
    def out_channels(self) -> int:
        return self.config.out_channels

    def forward(
        self, points: torch.Tensor, order: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.forward_many([points], [order])[0]

    def forward_many(
        self, clouds: list[torch.Tensor], orders: list[torch.Tensor]
    ) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """:meth:`forward` of several clouds ``(B, N_i, 3)`` (same ``B``): one evaluation for all
        of them on the fast eval path (fewer, larger operations: the template and the search
        region at batch 1), one call each otherwise (training keeps the BatchNorm statistics of
        each cloud apart)."""
        ragged = (
            not self.training and self.fast_eval and all(layer.fast_eval for layer in self.layers)
        )
        if not ragged and len(clouds) > 1:
            return [self.forward_many([p], [o])[0] for p, o in zip(clouds, orders, strict=True)]
        ordered = [self._ordered(p, o) for p, o in zip(clouds, orders, strict=True)]
        xyzs, orders = [x for x, _ in ordered], [o for _, o in ordered]
        # copies of a point (the env pads small clouds) are evaluated once on the ragged path
        firsts = [ops.first_copy_or_none(xyz) if ragged else None for xyz in xyzs]
        feats: list[torch.Tensor | None] = [None] * len(xyzs)
        ns = [xyz.shape[1] for xyz in xyzs]
        for layer in self.layers:
            ns = [n // 2 for n in ns]
            if ragged:  # layer inputs are prefixes of xyz and a first copy precedes its copies
                outs = layer.ragged(
                    xyzs,
                    feats,
                    ns,
                    [
                        None if f is None else f[:, : x.shape[1]]
                        for f, x in zip(firsts, xyzs, strict=True)
                    ],
                )
            else:
                outs = [layer(xyzs[0], feats[0], ns[0])]
            xyzs, feats = [o[0] for o in outs], [o[1] for o in outs]
        b = xyzs[0].shape[0]
        out = self.out(torch.cat([f.reshape(-1, f.shape[-1]) for f in feats]))
        results, start = [], 0
        for xyz, order, n in zip(xyzs, orders, ns, strict=True):
            results.append((xyz, out[start : start + b * n].view(b, n, -1), order[:, :n]))
            start += b * n
        return results

    def _ordered(
        self, points: torch.Tensor, order: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The points in sampling order and that order (FPS first when ``sampling="fps"``)."""
        if self.config.sampling == "fps":  # FPS picks first (in FPS order), then the rest
            first = ops.farthest_point_sample(ops.gather(points, order), points.shape[1] // 2)
            # rank: FPS position for picked points, after them the rest in order; a cloud with
            # fewer distinct points than picks makes FPS repeat an index (kept once)
            n = order.shape[1]
            picks = torch.arange(first.shape[1], device=order.device).expand_as(first)
            rank = torch.full_like(order, n).scatter_reduce_(1, first, picks, "amin")
            rank = rank * n + torch.arange(n, device=order.device)
            order = torch.gather(order, 1, rank.argsort(dim=1))
        return ops.gather(points, order), order
