"""BAT (Zheng et al., "Box-Aware Feature Enhancement for Single Object Tracking on Point
Clouds", ICCV 2021): Box-Cloud + box-aware feature fusion (BAFF) + the shared head.

* Box-Cloud (BC) of a point: its distances to the box centre and the 8 corners (9 values).
  Template seeds: computed from their box, which in our template frame is the canonical box
  ``(0, 0, 0, l, w, h, 0)`` with ``(l, w, h) = batch["size"]``. Search seeds: predicted by
  ``MLP [3+D, D, D, 9]`` from ``[xyz; feature]`` and supervised (smooth-L1, weight 1.0, on target
  seeds) with the BC of the ground-truth box.
* BAFF: each search seed takes its ``k = 4`` nearest template seeds in BC space; their
  ``[x_T; BC_T; f_T]`` (3 + 9 + D) go through ``MLP [3+9+D, 256, 256, 256]``, max over the ``k``,
  then ``MLP [256, 256, 256]`` -> ``Z`` (Open3DSOT's configuration: no search feature / search BC
  in the pair input, ``use_search_feature=False``).

The first BAFF layer sees only template quantities, so it is evaluated once per template seed and
gathered.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from envs.geometry import box_corners_torch
from trackers import ops
from trackers.base import MatchingConfig, MatchingTracker
from trackers.head import masked_mean, smooth_l1
from trackers.layers import MLP, max_pool
from trackers.p2b import P2B
from trackers.registry import register

__all__ = ["BAT", "BATConfig", "BoxAwareFusion", "box_cloud"]


def box_cloud(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Box-Cloud: ``points (B, N, 3)``, ``boxes (B, 7)`` -> ``(B, N, 9)`` distances to the centre
    and the 8 corners (``envs.geometry`` corner order)."""
    keypoints = torch.cat([boxes[:, None, :3], box_corners_torch(boxes)], dim=1)  # (B, 9, 3)
    return ops.pairwise_sqdist(points, keypoints).clamp_min(0).sqrt()


def canonical_boxes(size: torch.Tensor) -> torch.Tensor:
    """``size (B, 3)`` -> boxes ``(B, 7)`` centred at the origin with yaw 0."""
    zeros = size.new_zeros(size.shape[0], 3)
    return torch.cat([zeros, size, size.new_zeros(size.shape[0], 1)], dim=-1)


@dataclass
class BATConfig(MatchingConfig):
    """BAT hyper-parameters (BAT / Open3DSOT defaults)."""

    hidden_channels: int = 256
    out_channels: int = 256
    k: int = 4
    use_search_feature: bool = False


class BoxAwareFusion(nn.Module):
    """``(t_xyz, t_feat, t_bc (B,M_T,9), s_xyz, s_feat)`` -> ``(Z (B,M_S,out), s_bc (B,M_S,9))``."""

    def __init__(self, d: int, hidden: int, out: int, k: int, use_search_feature: bool) -> None:
        super().__init__()
        self.k, self.use_search_feature, self.d = k, use_search_feature, d
        self.bc_head = MLP([3 + d, d, d, 9], last_activation=False)
        extra = d if use_search_feature else 0
        self.mlp = MLP([3 + 9 + d + extra, hidden, hidden, hidden])
        self.post = MLP([hidden, hidden, out], last_activation=False)

    def forward(
        self,
        t_xyz: torch.Tensor,
        t_feat: torch.Tensor,
        t_bc: torch.Tensor,
        s_xyz: torch.Tensor,
        s_feat: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        s_bc = self.bc_head(torch.cat([s_xyz, s_feat], dim=-1))  # (B, M_S, 9)
        k = min(self.k, t_xyz.shape[1])
        _, nbr = ops.knn(k, s_bc.detach(), t_bc)  # (B, M_S, k) template seeds
        w, b = self.mlp.linear_params(0)
        t_in = torch.cat([t_xyz, t_bc, t_feat], dim=-1)
        per_t = F.linear(t_in, w[:, : t_in.shape[-1]], b)  # (B, M_T, H)
        pre = ops.group(per_t, nbr)  # (B, M_S, k, H)
        if self.use_search_feature:
            pre = pre + (s_feat @ w[:, t_in.shape[-1] :].t())[:, :, None, :]
        z = self.post(max_pool(self.mlp.forward_from(0, pre, fresh=True), 2))
        return z, s_bc


@register("bat")
class BAT(MatchingTracker):
    """BAT: backbone, BAFF with Box-Cloud, VoteNet proposal head, Box-Cloud loss."""

    config_class = BATConfig
    # BAT keeps P2B's head, its loss weights and its widths, and adds the Box-Cloud loss
    default_loss_weights: ClassVar[dict[str, float]] = {
        **P2B.default_loss_weights,
        "box_cloud": 1.0,
    }
    sizes: ClassVar[dict[str, dict[str, Any]]] = P2B.sizes

    def build_fusion(self, in_channels: int) -> tuple[nn.Module, int]:
        cfg = self.config
        if cfg.k < 1:
            raise ValueError(f"bat config: k must be >= 1, got {cfg.k}")
        fusion = BoxAwareFusion(
            in_channels, cfg.hidden_channels, cfg.out_channels, cfg.k, cfg.use_search_feature
        )
        return fusion, cfg.out_channels

    def fuse(self, t_xyz, t_feat, s_xyz, s_feat, batch):
        size = batch.get("size")
        if size is None:
            raise KeyError("BAT needs batch['size'] (B, 3) for the template Box-Cloud")
        t_bc = box_cloud(t_xyz, canonical_boxes(size.to(t_xyz.dtype)))
        z, s_bc = self.fusion(t_xyz, t_feat, t_bc, s_xyz, s_feat)
        return z, {"search_bc": s_bc, "template_bc": t_bc}

    def extra_losses(self, outputs, targets, seed_labels):
        gt = box_cloud(outputs["seed_xyz"], targets["search_box"].float())
        return {"box_cloud": masked_mean(smooth_l1(outputs["search_bc"], gt), seed_labels)}
