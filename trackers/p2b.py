"""P2B (Qi et al., "P2B: Point-to-Box Network for 3D Object Tracking in Point Clouds", CVPR
2020): target-specific feature augmentation (TFA) + the shared voting head.

TFA: for every template seed ``i`` and search seed ``j`` the input ``[cos(f_T,i, f_S,j); x_T,i;
f_T,i]`` (1 + 3 + D = 260 channels) goes through ``MLP [260, 256, 256, 256]``, max over the template
seeds, then ``MLP [256, 256, 256]`` (Conv-BN-ReLU, Conv) -> ``Z (B, M_S, 256)``.

The first Linear is linear in its concatenated input, so it is computed once per template seed
(``W_t [x_T; f_T] + b``) and the similarity enters as ``cos_ij * w_cos``, broadcast-added to form
the ``(B, M_T, M_S, 256)`` pre-activation (:meth:`P2BFusion.forward_plain`: training, and eval
with ``fast_eval=False``). The fast eval path (:meth:`P2BFusion.forward_fast`, the default in
eval) drops repeated template seeds and evaluates the TFA max by exact piecewise-linear
interpolation in the similarity (:mod:`trackers.p2b_knots`): the same function to float rounding.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from trackers import p2b_knots
from trackers.base import SLIM_BACKBONE, MatchingConfig, MatchingTracker
from trackers.layers import MLP, max_pool
from trackers.registry import register

__all__ = ["P2B", "P2BConfig", "P2BFusion"]


@dataclass
class P2BConfig(MatchingConfig):
    """P2B hyper-parameters; TFA hidden/out channels (P2B: 256 / 256)."""

    hidden_channels: int = 256
    out_channels: int = 256


class P2BFusion(nn.Module):
    """``(t_xyz (B,M_T,3), t_feat (B,M_T,D), s_feat (B,M_S,D))`` -> ``Z (B, M_S, out)``."""

    def __init__(self, d: int, hidden: int, out: int) -> None:
        super().__init__()
        self.fast_eval = True  # eval: de-duplicated seeds, knot interpolation (module doc)
        self.mlp = MLP([1 + 3 + d, hidden, hidden, hidden])
        self.post = MLP([hidden, hidden, out], last_activation=False)

    @staticmethod
    def cosine(t_feat: torch.Tensor, s_feat: torch.Tensor) -> torch.Tensor:
        """Cosine similarity of every pair -> ``(B, M_T, M_S)`` (zero vectors give 0)."""
        t = F.normalize(t_feat, dim=-1, eps=1e-8)
        return t @ F.normalize(s_feat, dim=-1, eps=1e-8).transpose(1, 2)

    def forward(
        self, t_xyz: torch.Tensor, t_feat: torch.Tensor, s_feat: torch.Tensor
    ) -> torch.Tensor:
        if self.training or not self.fast_eval:
            return self.forward_plain(t_xyz, t_feat, s_feat)
        return self.forward_fast(t_xyz, t_feat, s_feat)

    def first_layer(
        self, t_xyz: torch.Tensor, t_feat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """First-layer template part ``a (B, M_T, H)`` and similarity weight ``w (H,)``."""
        w, b = self.mlp.linear_params(0)
        return F.linear(torch.cat([t_xyz, t_feat], dim=-1), w[:, 1:], b), w[:, 0]

    def forward_plain(
        self, t_xyz: torch.Tensor, t_feat: torch.Tensor, s_feat: torch.Tensor
    ) -> torch.Tensor:
        """The TFA MLP on every (template seed, search seed) pair, max over template seeds."""
        a, w = self.first_layer(t_xyz, t_feat)
        cos = self.cosine(t_feat, s_feat)  # (B, M_T, M_S)
        pre = torch.addcmul(a[:, :, None, :], cos[..., None], w)  # (B, M_T, M_S, H)
        return self.post(max_pool(self.mlp.forward_from(0, pre, fresh=True), 1))

    def forward_fast(
        self, t_xyz: torch.Tensor, t_feat: torch.Tensor, s_feat: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`forward_plain` by knot interpolation (:mod:`trackers.p2b_knots`); every pair
        when the knots are too many."""
        t_xyz, t_feat = p2b_knots.unique_seeds(t_xyz, t_feat)
        cos = self.cosine(t_feat, s_feat)
        a, w = self.first_layer(t_xyz, t_feat)
        pre_max = p2b_knots.tfa_pre_max(self.mlp, a, w, cos)  # (B, M_S, H) or None
        if pre_max is None:
            pre = torch.addcmul(a[:, :, None, :], cos[..., None], w)
            return self.post(max_pool(self.mlp.forward_from(0, pre, fresh=True), 1))
        return self.post(self.mlp.finish(len(self.mlp.linears) - 1, pre_max, fresh=True))


@register("p2b")
class P2B(MatchingTracker):
    """P2B: backbone, TFA, VoteNet proposal head."""

    config_class = P2BConfig
    default_loss_weights: ClassVar[dict[str, float]] = {
        "vote": 1.0,
        "seed": 0.2,
        "objectness": 1.5,
        "box": 0.2,
    }
    sizes: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        "slim": {
            "backbone": SLIM_BACKBONE,
            "hidden_channels": 64,
            "out_channels": 128,
            "head": {"vote_channels": 128},
        },
    }

    def build_fusion(self, in_channels: int) -> tuple[nn.Module, int]:
        cfg = self.config
        return P2BFusion(in_channels, cfg.hidden_channels, cfg.out_channels), cfg.out_channels

    def fuse(self, t_xyz, t_feat, s_xyz, s_feat, batch):
        return self.fusion(t_xyz, t_feat, s_feat), {}
