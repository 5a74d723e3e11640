"""GPT (Park, Seong, Jang, Kim, "Graph-Based Point Tracker for 3D Object Tracking in Point Clouds",
AAAI 2022): graph feature augmentation (GFA) with the improved target clue (ITC) + the shared
voting head.

* Nodes (Eq. 1): ``f_T^node = phi(f_T^seed)``, ``f_S^node = varphi(f_S^seed)``, two different
  ``1x1`` convolutions ``D_seed = 256 -> D_node = 128``.
* Bipartite graph: each search node receives edges from its ``k = 16`` nearest template nodes in
  node-feature space (Euclidean).
* ITC: a template voting module ``MLP [3+256, 256, 256, 3+256]`` gives template votes
  ``y_T = x_T + dx_T`` and ``f_T^vote = f_T^seed + df_T``; a ``1x1`` convolution maps the vote
  feature to ``D_ITC = 128`` (``f_bar_T^vote``).
* EdgeConv (Eq. 6): ``max_i MLP([x_T,i; f_T,i^node - f_S,j^node; f_bar_T,i^vote])`` with
  ``MLP [3+128+128, 256, 256, 256]`` -> target-specific search nodes ``Z (B, M_S, 256)``
  (Eq. 5 with ``use_itc=False``: ``f_T^node`` in place of ``f_bar_T^vote``).
* Losses (Eq. 10): search vote 0.9, template vote 0.1 (Eq. 9: every template seed votes for the
  template centre, ``targets["template_centers"]`` at the seeds; no on-target mask, as the paper),
  seed score 0.2, box 0.2, objectness 1.5. Both vote terms use the shared smooth-L1 vote loss.

The EdgeConv's first layer is linear in its input, so its template part ``W_x x_T + W_d f_T +
W_v f_bar + b`` is computed once per template node and its search part ``W_d f_S`` once per
search node; an edge's pre-activation is their difference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from trackers import ops
from trackers.base import SLIM_BACKBONE, MatchingConfig, MatchingTracker
from trackers.head import smooth_l1
from trackers.layers import MLP, dense_max
from trackers.registry import register

__all__ = ["GPT", "GPTConfig", "GraphFusion"]


@dataclass
class GPTConfig(MatchingConfig):
    """GPT hyper-parameters (the paper's Implementation Details)."""

    node_channels: int = 128
    itc_channels: int = 128
    out_channels: int = 256
    k: int = 16
    use_itc: bool = True


class GraphFusion(nn.Module):
    """``(t_xyz, t_feat, s_feat)`` -> ``(Z (B, M_S, out), template votes (B, M_T, 3))``."""

    def __init__(self, d: int, node: int, itc: int, out: int, k: int, use_itc: bool) -> None:
        super().__init__()
        self.k, self.node, self.use_itc = k, node, use_itc
        self.phi = nn.Linear(d, node)
        self.varphi = nn.Linear(d, node)
        if use_itc:
            self.template_vote = MLP([3 + d, d, d, 3 + d], last_activation=False)
            self.itc = nn.Linear(d, itc)
        clue = itc if use_itc else node
        self.edge = MLP([3 + node + clue, out, out, out])

    def forward(
        self, t_xyz: torch.Tensor, t_feat: torch.Tensor, s_feat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        f_t, f_s = self.phi(t_feat), self.varphi(s_feat)  # (B, M_T, n), (B, M_S, n)
        votes = None
        if self.use_itc:
            seed = torch.cat([t_xyz, t_feat], dim=-1)
            vote = seed + self.template_vote(seed)
            votes, clue = vote[..., :3], self.itc(vote[..., 3:])
        else:
            clue = f_t
        k = min(self.k, f_t.shape[1])
        _, nbr = ops.knn(k, f_s.detach(), f_t.detach())  # (B, M_S, k) template nodes
        w, b = self.edge.linear_params(0)
        n = self.node
        per_t = F.linear(torch.cat([t_xyz, f_t, clue], dim=-1), w, b)  # (B, M_T, out)
        per_s = f_s @ w[:, 3 : 3 + n].t()  # (B, M_S, out)
        pre = ops.group(per_t, nbr) - per_s[:, :, None, :]  # (B, M_S, k, out)
        return dense_max(self.edge, pre, 2), votes


@register("gpt")
class GPT(MatchingTracker):
    """GPT: backbone, GFA with ITC, VoteNet proposal head, template-vote loss."""

    config_class = GPTConfig
    default_loss_weights: ClassVar[dict[str, float]] = {
        "vote": 0.9,
        "template_vote": 0.1,
        "seed": 0.2,
        "box": 0.2,
        "objectness": 1.5,
    }
    sizes: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        "slim": {
            "backbone": SLIM_BACKBONE,
            "node_channels": 64,
            "itc_channels": 64,
            "out_channels": 128,
            "head": {"vote_channels": 128},
        },
    }

    def build_fusion(self, in_channels: int) -> tuple[nn.Module, int]:
        cfg = self.config
        if cfg.k < 1:
            raise ValueError(f"gpt config: k must be >= 1, got {cfg.k}")
        if not cfg.use_itc and "template_vote" in cfg.loss_weights:
            cfg.loss_weights = {k: v for k, v in cfg.loss_weights.items() if k != "template_vote"}
        fusion = GraphFusion(
            in_channels, cfg.node_channels, cfg.itc_channels, cfg.out_channels, cfg.k, cfg.use_itc
        )
        return fusion, cfg.out_channels

    def fuse(self, t_xyz, t_feat, s_xyz, s_feat, batch):
        z, votes = self.fusion(t_xyz, t_feat, s_feat)
        return z, ({"template_votes": votes} if votes is not None else {})

    def extra_losses(self, outputs, targets, seed_labels):
        if "template_votes" not in outputs:
            return {}
        if "template_centers" not in targets:
            raise KeyError("GPT's template-vote loss needs targets['template_centers'] (B, 512, 3)")
        centres = ops.gather(targets["template_centers"].float(), outputs["template_seed_idx"])
        return {"template_vote": smooth_l1(outputs["template_votes"], centres).mean(-1)}
