"""P2B (Qi et al., CVPR 2020): target-specific feature augmentation (TFA) + the shared head.

TFA: for every template seed ``i`` and search seed ``j`` the input ``[cos(f_T,i, f_S,j); x_T,i;
f_T,i]`` (1 + 3 + D = 260 channels) goes through ``MLP [260, 256, 256, 256]``, max over the template
seeds, then ``MLP [256, 256, 256]`` (Conv-BN-ReLU, Conv) -> ``Z (B, M_S, 256)``.

Speed: the first Linear is linear in its concatenated input, so it is computed once per template
seed (``W_t [x_T; f_T] + b``) and the similarity enters as ``cos_ij * w_cos`` - broadcast-added to
form the ``(B, M_T, M_S, 256)`` pre-activation (:meth:`P2BFusion.forward_naive` is the plain
concatenation; the tests check both agree). In eval mode repeated template seeds (copies of one
padded input point) are dropped first (:func:`unique_seeds`): the max over template seeds is the
same, and sparse targets - heavily padded templates - cost less.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from trackers import ops
from trackers.base import Tracker, TrackerConfig
from trackers.layers import MLP

__all__ = ["P2B", "P2BConfig", "P2BFusion"]


@dataclass
class P2BConfig(TrackerConfig):
    """P2B hyper-parameters; TFA hidden/out channels (P2B: 256 / 256)."""

    hidden_channels: int = 256
    out_channels: int = 256


def unique_seeds(xyz: torch.Tensor, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Drop repeated seeds ``(B, M, 3)``, ``(B, M, D)`` -> ``(B, U, 3)``, ``(B, U, D)``.

    Copies of one input point (the env pads small clouds with copies) are seeds with equal
    coordinates and - same centre, same neighbourhood - equal features, so a max over seeds is
    unchanged without them. ``U`` is the largest count of distinct seeds in the batch; rows with
    fewer keep some copies (harmless for a max).
    """
    same = (xyz[:, :, None, :] == xyz[:, None, :, :]).all(-1)  # (B, M, M)
    earlier = torch.ones_like(same[0], dtype=torch.bool).tril(-1)
    first = ~(same & earlier).any(-1)  # (B, M): no earlier equal seed
    u = int(first.sum(1).max())
    if u == xyz.shape[1]:
        return xyz, feats
    keep = torch.sort((~first).to(torch.uint8), dim=1, stable=True).indices[:, :u]
    return ops.gather(xyz, keep), ops.gather(feats, keep)


class P2BFusion(nn.Module):
    """``(t_xyz (B,M_T,3), t_feat (B,M_T,D), s_feat (B,M_S,D))`` -> ``Z (B, M_S, out)``."""

    def __init__(self, d: int, hidden: int, out: int) -> None:
        super().__init__()
        self.dedupe_eval = True
        self.mlp = MLP([1 + 3 + d, hidden, hidden, hidden])
        self.post = MLP([hidden, hidden, out], last_activation=False)

    @staticmethod
    def cosine(t_feat: torch.Tensor, s_feat: torch.Tensor) -> torch.Tensor:
        """Cosine similarity of every pair -> ``(B, M_T, M_S)`` (zero vectors give 0)."""
        t = F.normalize(t_feat, dim=-1, eps=1e-8)
        return t @ F.normalize(s_feat, dim=-1, eps=1e-8).transpose(1, 2)

    def forward(self, t_xyz: torch.Tensor, t_feat: torch.Tensor,
                s_feat: torch.Tensor) -> torch.Tensor:
        if not self.training and self.dedupe_eval:
            t_xyz, t_feat = unique_seeds(t_xyz, t_feat)
        cos = self.cosine(t_feat, s_feat)
        w, b = self.mlp.linear_params(0)
        t_part = F.linear(torch.cat([t_xyz, t_feat], dim=-1), w[:, 1:], b)  # (B, M_T, H)
        pre = torch.addcmul(t_part[:, :, None, :], cos[..., None], w[:, 0])  # (B, M_T, M_S, H)
        h = self.mlp.forward_from(0, pre).amax(dim=1)  # (B, M_S, H)
        return self.post(h)

    def forward_naive(self, t_xyz: torch.Tensor, t_feat: torch.Tensor,
                      s_feat: torch.Tensor) -> torch.Tensor:
        """Reference: the explicit ``(B, M_T, M_S, 260)`` concatenation."""
        cos = self.cosine(t_feat, s_feat)
        mt, ms = cos.shape[1], cos.shape[2]
        t = torch.cat([t_xyz, t_feat], dim=-1)[:, :, None, :].expand(-1, mt, ms, -1)
        x = torch.cat([cos[..., None], t], dim=-1)
        return self.post(self.mlp(x).amax(dim=1))


class P2B(Tracker):
    """P2B: backbone, TFA, VoteNet proposal head."""

    name = "p2b"
    config_class = P2BConfig
    default_loss_weights = {"vote": 1.0, "seed": 0.2, "objectness": 1.5, "box": 0.2}

    def build_fusion(self) -> None:
        cfg = self.config
        self.fusion = P2BFusion(self.backbone.out_channels, cfg.hidden_channels, cfg.out_channels)
        self.fused_channels = cfg.out_channels

    def fuse(self, t_xyz, t_feat, s_xyz, s_feat, batch):
        return self.fusion(t_xyz, t_feat, s_feat), {}
