"""The proposal head shared by P2B, BAT and GPT (P2B's VoteNet RPN) and its losses.

From the fused search features ``Z (B, M, D)`` at the search seeds ``xyz (B, M, 3)``:

* per-seed target score (logit) ``MLP [D, D, D, 1]``;
* Hough voting ``MLP [3+D, D, D, 3+D]``: a vote ``[xyz; Z] + offset`` per seed;
* proposals: the first ``num_proposals`` votes (seeds are in random order, so this is random
  sampling of votes) are cluster centres; each clusters the votes within ``cluster_radius``
  (ball query, ``cluster_votes`` slots); ``MLP [3+1+D, V, V, V]`` on ``[vote_xyz - centre;
  sigmoid(score); vote_feature]``, max over the cluster, then ``MLP [V, V, V, 5]`` -> centre
  offset (3), yaw, objectness logit. On the fast eval path (``fast_eval=True``) the cluster max
  runs over the real members only (:func:`trackers.layers.grouped_max`; the padding slots repeat
  a member: same max); the plain path evaluates the dense ``(B, P, k)`` groups.

A proposal is ``(x, y, z, yaw)`` of the target box in the search (reference-box) frame, which is
exactly the env's action ``(dx, dy, dz, dyaw)``. Internally the yaw output is in degrees by
default (``yaw_unit="deg"``, as P2B's and Open3DSOT's regression targets, which sets the scale of
the box loss); ``outputs["proposals"]`` is always in radians.

Losses (per sample, ``(B,)``; Open3DSOT's definitions, normalised per sample instead of per batch):
``vote`` smooth-L1 of vote xyz to the GT centre on target seeds; ``seed`` BCE of seed scores;
``objectness`` BCE (``pos_weight`` 2) of proposal scores, positive when the cluster centre is
within 0.3 m of the GT centre, negative beyond 0.6 m, ignored between (:func:`proposal_labels`;
``positive_fraction > 0`` widens both radii for large boxes); ``box`` smooth-L1 of
``(x, y, z, yaw)`` to the GT box on positive proposals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from trackers import ops
from trackers.layers import MLP, grouped_max, max_pool

__all__ = ["HeadConfig", "VotingHead", "head_losses", "proposal_labels", "smooth_l1"]


@dataclass
class HeadConfig:
    """Proposal-head hyper-parameters (defaults: P2B's)."""

    vote_channels: int = 256
    num_proposals: int = 64
    cluster_radius: float = 0.3
    cluster_votes: int = 16
    yaw_unit: str = "deg"
    positive_radius: float = 0.3
    negative_radius: float = 0.6
    # > 0: the radii grow to f (positive) and 2 f (negative) times half the box's xy diagonal
    # where that is larger (a size-relative label; 0 = the papers' fixed radii). f = 0.2 cost
    # slim BAT 24 Van Success from scratch (docs/notes/checkpoints-history.md): kept to
    # reproduce that
    positive_fraction: float = 0.0
    objectness_pos_weight: float = 2.0

    def __post_init__(self) -> None:
        if self.yaw_unit not in ("deg", "rad"):
            raise ValueError(f"head: yaw_unit must be 'deg' or 'rad', got {self.yaw_unit!r}")
        if self.num_proposals < 1 or self.cluster_votes < 1 or self.cluster_radius <= 0:
            raise ValueError("head: num_proposals, cluster_votes, cluster_radius must be positive")
        if not 0 < self.positive_radius <= self.negative_radius:
            raise ValueError("head: need 0 < positive_radius <= negative_radius")
        if not self.positive_fraction >= 0:
            raise ValueError(
                f"head: positive_fraction must be >= 0, got {self.positive_fraction!r}"
            )


class VotingHead(nn.Module):
    """``forward(xyz (B, M, 3), Z (B, M, D))`` -> dict of head outputs (see module doc)."""

    def __init__(self, in_channels: int, config: HeadConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or HeadConfig()
        d, v = in_channels, config.vote_channels
        self.cls = MLP([d, d, d, 1], last_activation=False)
        self.vote = MLP([3 + d, d, d, 3 + d], last_activation=False)
        self.aggregate = MLP([3 + 1 + d, v, v, v])
        self.proposal = MLP([v, v, v, 5], last_activation=False)
        self.yaw_scale = math.pi / 180.0 if config.yaw_unit == "deg" else 1.0
        self.fast_eval = True  # eval: cluster max over the real members only

    def forward(self, xyz: torch.Tensor, z: torch.Tensor) -> dict[str, torch.Tensor]:
        n_prop = min(self.config.num_proposals, xyz.shape[1])
        seed_logits, vote_xyz, vote_feat, per_vote = self._votes(xyz, z)
        centres = vote_xyz[:, :n_prop]  # (B, P, 3)
        raw = self._clusters(vote_xyz, per_vote, centres)  # (B, P, 5)
        box_raw = torch.cat([centres + raw[..., :3], raw[..., 3:4]], dim=-1)  # yaw in yaw_unit
        return {
            "seed_logits": seed_logits,
            "votes": vote_xyz,
            "vote_features": vote_feat,
            "proposal_centers": centres,
            "box_raw": box_raw,
            "proposals": self._radians(box_raw),
            "scores": raw[..., 4],
        }

    def proposal_at(
        self, xyz: torch.Tensor, z: torch.Tensor, votes: torch.Tensor, index: torch.Tensor
    ) -> torch.Tensor:
        """``forward(xyz, z)["proposals"]`` at ``index (B,)`` -> ``(B, 4)``, evaluating only what
        that proposal depends on: its centre's vote and its cluster members' votes, the members
        found among ``votes (B, M, 3)`` (``forward``'s, no gradient needed). The same values to
        float rounding and the same gradient in the weights and ``z`` (the other proposals add
        nothing to it): RL's update differentiates the one proposal the decision step executes
        per state, at a few per cent of the head's work. Eval mode only (in training, BatchNorm's
        statistics over one cluster would not be those over all)."""
        if self.training:
            raise RuntimeError("VotingHead.proposal_at: eval mode only (BatchNorm statistics)")
        b, m = xyz.shape[:2]
        rows = torch.arange(b, device=index.device)
        group, point = ops.ball_query_pairs(  # (P,): centre b, member seed b * M + j
            self.config.cluster_radius,
            self.config.cluster_votes,
            votes,
            votes[rows, index][:, None],
        )
        seeds = torch.cat([point, rows * m + index])  # the members, then the centres
        _, vote_xyz, _, per_vote = self._votes(  # index_select: its backward is the cheaper
            xyz.reshape(b * m, 3).index_select(0, seeds)[None],
            z.reshape(b * m, -1).index_select(0, seeds)[None],
        )
        centres = vote_xyz[0, len(point) :, None]  # (B, 1, 3)
        cluster = grouped_max(
            self.aggregate,
            per_vote[:, : len(point)],
            self._per_centre(centres),
            group,
            torch.arange(len(point), device=point.device),
        )
        raw = self.proposal(cluster)  # (B, 1, 5)
        return self._radians(torch.cat([centres + raw[..., :3], raw[..., 3:4]], dim=-1))[:, 0]

    def _votes(
        self, xyz: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Seed logits ``(B, M)``, votes ``(B, M, 3)`` and ``(B, M, D)``, and each vote's part of
        the first aggregation layer ``(B, M, V)``: ``W [xyz; sigmoid(score); feature] + b`` (the
        layer decomposed into a per-vote and a per-centre term ``W_x c``)."""
        seed_logits = self.cls(z).squeeze(-1)  # (B, M)
        seed_feat = torch.cat([xyz, z], dim=-1)
        vote = seed_feat + self.vote(seed_feat)  # (B, M, 3 + D)
        vote_xyz, vote_feat = vote[..., :3], vote[..., 3:]
        w, b = self.aggregate.linear_params(0)
        per_vote = F.linear(
            torch.cat([vote_xyz, torch.sigmoid(seed_logits)[..., None], vote_feat], dim=-1), w, b
        )
        return seed_logits, vote_xyz, vote_feat, per_vote

    def _clusters(
        self, vote_xyz: torch.Tensor, per_vote: torch.Tensor, centres: torch.Tensor
    ) -> torch.Tensor:
        """The raw outputs ``(B, P, 5)`` (centre offset, yaw, objectness logit) of the clusters
        of votes around ``centres (B, P, 3)``."""
        per_centre = self._per_centre(centres)
        radius, k = self.config.cluster_radius, self.config.cluster_votes
        if self.training or not self.fast_eval:  # dense: BatchNorm statistics over every slot
            idx = ops.ball_query(radius, k, vote_xyz, centres)  # (B, P, k)
            pre = ops.group(per_vote, idx) - per_centre[:, :, None, :]  # (B, P, k, V)
            cluster = max_pool(self.aggregate.forward_from(0, pre, fresh=True), 2)  # (B, P, V)
        else:  # the real cluster members only: the same max, less work
            group, point = ops.ball_query_pairs(radius, k, vote_xyz, centres)
            cluster = grouped_max(self.aggregate, per_vote, per_centre, group, point)
        return self.proposal(cluster)

    def _per_centre(self, centres: torch.Tensor) -> torch.Tensor:
        """The per-centre term ``W_x c`` of the decomposed first aggregation layer (see
        :meth:`_votes`), ``(..., 3)`` -> ``(..., V)``."""
        w, _ = self.aggregate.linear_params(0)
        return centres @ w[:, :3].t()

    def _radians(self, box_raw: torch.Tensor) -> torch.Tensor:
        """``(..., 4)`` boxes with the yaw in ``yaw_unit`` -> in radians."""
        return torch.cat([box_raw[..., :3], box_raw[..., 3:4] * self.yaw_scale], dim=-1)


def smooth_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Elementwise smooth-L1 (beta 1), averaged over the last dimension."""
    return F.smooth_l1_loss(pred, target, reduction="none").mean(-1)


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample mean of ``values (B, ...)`` over ``mask`` -> ``(B,)``; 0 where mask is empty."""
    dims = tuple(range(1, values.dim()))
    return (values * mask).sum(dims) / (mask.sum(dims) + 1e-6)


def proposal_labels(
    proposal_centers: torch.Tensor, search_box: torch.Tensor, config: HeadConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(positive, counted)``, each ``(B, P)`` 0/1: proposals whose centre ``(B, P, 3)`` is
    within the positive radius of the GT centre (``search_box (B, 7)``), and those that enter
    the objectness loss (positive, or beyond the negative radius). The radii are
    ``config.positive_radius`` / ``negative_radius``, or ``f`` / ``2 f`` times half the box's xy
    diagonal where larger (``f = config.positive_fraction``)."""
    dist = (proposal_centers - search_box[:, None, :3]).square().sum(-1).add(1e-6).sqrt()
    positive_r, negative_r = config.positive_radius, config.negative_radius
    if config.positive_fraction > 0:
        half_diagonal = 0.5 * torch.hypot(search_box[:, 3], search_box[:, 4])[:, None]  # (B, 1)
        scaled = config.positive_fraction * half_diagonal
        positive_r = scaled.clamp_min(positive_r)
        negative_r = (2 * scaled).clamp_min(negative_r)
    positive = (dist < positive_r).float()
    return positive, positive + (dist > negative_r).float()


def head_losses(
    outputs: dict[str, torch.Tensor],
    search_box: torch.Tensor,
    seed_labels: torch.Tensor,
    config: HeadConfig,
) -> dict[str, torch.Tensor]:
    """Per-sample head losses ``(B,)``: ``vote``, ``seed``, ``objectness``, ``box``.

    ``search_box (B, 7)`` GT box in the search frame, ``seed_labels (B, M)`` 0/1 at the seeds.
    """
    centre = search_box[:, None, :3]
    yaw_scale = math.pi / 180.0 if config.yaw_unit == "deg" else 1.0
    votes = outputs["votes"]
    vote = masked_mean(smooth_l1(votes, centre.expand_as(votes)), seed_labels)
    seed = F.binary_cross_entropy_with_logits(
        outputs["seed_logits"], seed_labels, reduction="none"
    ).mean(-1)
    centres = outputs["proposal_centers"]
    positive, counted = proposal_labels(centres, search_box, config)
    pos_weight = torch.tensor(
        config.objectness_pos_weight, device=centres.device, dtype=centres.dtype
    )
    obj = F.binary_cross_entropy_with_logits(
        outputs["scores"], positive, reduction="none", pos_weight=pos_weight
    )
    objectness = masked_mean(obj, counted)
    target = torch.cat([search_box[:, :3], search_box[:, 6:7] / yaw_scale], dim=-1)  # (B, 4)
    box_raw = outputs["box_raw"]
    box = masked_mean(smooth_l1(box_raw, target[:, None].expand_as(box_raw)), positive)
    return {"vote": vote, "seed": seed, "objectness": objectness, "box": box}
