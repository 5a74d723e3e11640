"""Batch reductions of the trackers' per-sample losses (``TrainConfig.loss_reduction``).

The trackers' ``loss`` gives every term as a per-sample mean ``l_i`` over that sample's counted
elements (target seeds for ``vote`` and ``box_cloud``, every seed for ``seed``, the proposals
beyond the ignore band for ``objectness``, the positive proposals for ``box``, the template
seeds for GPT's ``template_vote``); ``c_i`` is that number of elements.

* ``"sample"`` (recipe v1): the mean over samples of the weighted total, ``mean_i sum_k a_k
  l_ik`` (or ``sum_i w_i sum_k a_k l_ik`` with the -W weights), every sample counting alike.
* ``"pooled"`` (recipe v2, Open3DSOT's): each term is a mean over all the batch's counted
  elements; with per-sample weights ``w_i`` (the -W decorrelation weights; 1 without), each
  sample's elements weigh ``w_i``:

      pooled_k = sum_i w_i c_ik l_ik / sum_i w_i c_ik      (0 when no element counts)

  and the objective is ``sum_k a_k pooled_k`` (``a_k`` the tracker's loss weights). With
  ``w_i = 1`` this is ``sum of the elements' losses / number of elements`` over the batch (up
  to the per-sample 1e-6 guard of the trackers' means). A sample with many target points thus
  weighs more in ``vote`` than one with few, as in Open3DSOT. Under DDP the denominators are
  summed over the processes, so the result is the pooled loss of the global batch (as one
  process would compute it).

Models that are not :class:`trackers.base.MatchingTracker` (no known element counts) pool their
``total`` with ``c_i = 1``: the (weighted) mean over samples.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch

from trackers.base import MatchingTracker
from trackers.head import proposal_labels

__all__ = ["LOSS_REDUCTIONS", "loss_counts", "pooled", "pooled_objective"]

LOSS_REDUCTIONS = ("sample", "pooled")
SumOverRanks = Callable[[torch.Tensor], torch.Tensor]
"""An in-place all-reduce sum over the DDP processes (returns its argument)."""


def pooled(
    per_sample: torch.Tensor, counts: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """``sum_i w_i c_i l_i / sum_i w_i c_i`` of per-sample means ``l (B,)`` over ``c (B,)``
    elements each, weights ``w (B,)`` (1 when None); 0 when no element counts."""
    return _pooled_terms([per_sample], [counts], weights)[0]


def _pooled_terms(
    per_sample: list[torch.Tensor],
    counts: list[torch.Tensor],
    weights: torch.Tensor | None,
    sum_over_ranks: SumOverRanks | None = None,
    world: int = 1,
) -> torch.Tensor:
    """The pooled value ``(K,)`` of K terms; with ``sum_over_ranks`` the denominators are the
    whole DDP batch's (one all-reduce) and the numerators scaled by ``world``, so the gradient
    average DDP takes is the pooled loss of the global batch."""
    nums, dens = [], []
    for loss, count in zip(per_sample, counts, strict=True):
        wc = count.to(loss.dtype)
        if weights is not None:
            wc = wc * weights.to(loss.dtype)
        nums.append((wc * loss).sum())
        dens.append(wc.sum())
    num, den = torch.stack(nums), torch.stack(dens).detach()
    if sum_over_ranks is not None:
        den = sum_over_ranks(den.clone())
        num = num * world
    return torch.where(den > 0, num / den.clamp_min(torch.finfo(den.dtype).tiny), num * 0.0)


def loss_counts(
    model: torch.nn.Module, outputs: Mapping[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The element counts ``c_ik (B,)`` of every loss term of a matching tracker (P2B, BAT,
    GPT: the masks of :func:`trackers.head.head_losses` and the trackers' extra terms)."""
    seed_labels = torch.gather(targets["search_labels"].float(), 1, outputs["seed_idx"])
    positive, counted = proposal_labels(
        outputs["proposal_centers"], targets["search_box"].float(), model.config.head
    )
    b = seed_labels.shape[0]
    counts = {
        "vote": seed_labels.sum(1),
        "seed": torch.full((b,), float(seed_labels.shape[1]), device=seed_labels.device),
        "objectness": counted.sum(1),
        "box": positive.sum(1),
        "box_cloud": seed_labels.sum(1),
    }
    if "template_votes" in outputs:
        counts["template_vote"] = torch.full(
            (b,), float(outputs["template_votes"].shape[1]), device=seed_labels.device
        )
    return counts


def pooled_objective(
    model: torch.nn.Module,
    losses: Mapping[str, torch.Tensor],
    outputs: Mapping[str, torch.Tensor],
    targets: Mapping[str, torch.Tensor],
    weights: torch.Tensor | None = None,
    sum_over_ranks: SumOverRanks | None = None,
    world: int = 1,
) -> torch.Tensor:
    """The ``"pooled"`` objective (module docstring) of ``model.loss``'s per-sample ``losses``;
    under DDP (``sum_over_ranks``: an in-place all-reduce sum, ``world`` processes) pooled over
    the global batch."""
    if not isinstance(model, MatchingTracker):
        total = losses["total"]
        return _pooled_terms([total], [torch.ones_like(total)], weights, sum_over_ranks, world)[0]
    counts = loss_counts(model, outputs, targets)
    loss_weights = model.config.loss_weights
    missing = sorted(k for k in loss_weights if k not in counts)
    if missing:
        raise KeyError(
            f"pooled loss: no element counts for terms {', '.join(missing)} of "
            f"{type(model).__name__}"
        )
    keys = list(loss_weights)
    values = _pooled_terms(
        [losses[k] for k in keys], [counts[k] for k in keys], weights, sum_over_ranks, world
    )
    return sum(loss_weights[k] * values[i] for i, k in enumerate(keys))
