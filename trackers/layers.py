"""Shared pointwise MLP (the ``1x1`` convolutions of PointNet++ code) on channels-last tensors.

``MLP([c0, c1, ..., cn])`` is ``n`` layers ``Linear -> BatchNorm -> ReLU``; with
``last_activation=False`` the last layer is a plain ``Linear`` with bias (an output layer). Inputs
are ``(..., c0)``; BatchNorm normalises over every leading position (as ``BatchNorm2d`` over
``(B, C, M, k)`` does in the reference code).

Two eval paths, chosen by the module's ``fast_eval`` flag (set for a whole tracker by
:attr:`trackers.base.Tracker.fast_eval`, or :func:`set_fast_eval` on any module tree):

* plain (``fast_eval=False``): ``Linear -> BatchNorm (running statistics) -> ReLU``, the training
  computation with the running statistics - the path to read and debug;
* fast (``fast_eval=True``, the default): each BatchNorm folded into its Linear (one matmul, no
  extra pass; cached while the weights do not change) - the same function up to float rounding.

The first layer can be evaluated separately (:meth:`MLP.linear_params` + :meth:`MLP.forward_from`)
so callers can decompose it over the parts of a concatenated input (the linear-first-layer trick
used by the set abstraction, the P2B fusion, the GPT edge convolution and the proposal
aggregation). No method modifies its input tensors.

:func:`grouped_max` evaluates ``max over a group of MLP(pre)`` on the real members of ball-query
groups only (ragged), for the set abstraction and the proposal aggregation on the fast path.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["MLP", "dense_max", "grouped_max", "max_pool", "set_fast_eval"]


def set_fast_eval(module: nn.Module, enabled: bool) -> None:
    """Set ``fast_eval`` on every submodule of ``module`` (itself included) that has the flag."""
    for sub in module.modules():
        if hasattr(sub, "fast_eval"):
            sub.fast_eval = bool(enabled)


def max_pool(x: torch.Tensor, dim: int) -> torch.Tensor:
    """The max of ``x`` over ``dim`` (the PointNet pooling): ``amax``'s values, with the
    gradient of ``max`` - all of it to the first maximal element, as the reference code's
    ``max_pool2d`` - instead of ``amax``'s even split among ties. Its backward is a scatter
    through the indices instead of comparing every element with the max (~1.5x faster pooling
    and ReLU forward + backward in CPU training). Ties happen at copies of a point (padded
    crops): the split sent each copy ``g / c`` and their shared parameters the sum of those,
    which equals ``g`` up to rounding. Without autograd it is ``amax`` itself: the same values,
    and ~20x faster on CPU over a middle dimension (``max`` tracks the indices)."""
    if not x.requires_grad:
        return x.amax(dim=dim)
    return x.max(dim=dim).values


class MLP(nn.Module):
    """Pointwise MLP ``(..., channels[0]) -> (..., channels[-1])``."""

    def __init__(self, channels: Sequence[int], last_activation: bool = True) -> None:
        super().__init__()
        if len(channels) < 2:
            raise ValueError(f"an MLP needs at least two channel sizes, got {list(channels)}")
        self.channels = tuple(int(c) for c in channels)
        n = len(self.channels) - 1
        self.activated = tuple(i < n - 1 or last_activation for i in range(n))
        self.linears = nn.ModuleList(
            nn.Linear(self.channels[i], self.channels[i + 1], bias=not self.activated[i])
            for i in range(n)
        )
        self.norms = nn.ModuleList(
            nn.BatchNorm1d(self.channels[i + 1]) if self.activated[i] else nn.Identity()
            for i in range(n)
        )
        # the same modules as a plain tuple: ModuleList indexing costs ~4 us, and a forward at
        # batch 1 asks for every layer's parameters
        self._layers = tuple(zip(self.linears, self.norms, strict=True))
        self.fast_eval = True  # eval: BatchNorm folded into the Linear (see the module doc)
        # layer -> (source tensors, their versions and addresses, folded weight and bias)
        self._folded: dict[int, tuple[tuple, list, tuple[torch.Tensor, torch.Tensor]]] = {}

    def linear_params(self, i: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Weight ``(c_out, c_in)`` and bias of layer ``i``; on the fast eval path with its
        BatchNorm folded in (:meth:`finish` then applies only the ReLU).

        Without autograd the folded pair is cached, keyed by the tensors it is made of, their
        version counters (any in-place update - an optimiser step, ``load_state_dict`` -
        refolds) and storage addresses (``.to()`` replaces a parameter's data): a forward at
        batch 1 would otherwise spend a good part of its time folding. The sources are read
        from the modules' parameter dicts (``nn.Module.__getattr__`` costs more than the check).
        """
        lin, norm = self._layers[i]
        if self.training or not self.fast_eval or not self.activated[i]:
            return lin.weight, lin.bias
        if torch.is_grad_enabled():  # a fresh fold: gradients reach the parameters
            return self._fold(i)
        lp, np_, nb = lin._parameters, norm._parameters, norm._buffers
        sources = (
            lp["weight"],
            lp["bias"],
            np_["weight"],
            np_["bias"],
            nb["running_mean"],
            nb["running_var"],
        )
        stamp = [None if t is None else (t._version, t.data_ptr()) for t in sources]
        cached = self._folded.get(i)
        if cached is None or cached[1] != stamp or not all(map(operator.is_, cached[0], sources)):
            cached = self._folded[i] = (sources, stamp, self._fold(i))
        return cached[2]

    def _fold(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Layer ``i``'s Linear with its BatchNorm (running statistics) folded in."""
        lin, norm = self._layers[i]
        scale = norm.weight * torch.rsqrt(norm.running_var + norm.eps)
        shift = norm.bias - norm.running_mean * scale
        if lin.bias is not None:
            shift = shift + lin.bias * scale
        return lin.weight * scale[:, None], shift

    def finish(self, i: int, pre: torch.Tensor, *, fresh: bool = False) -> torch.Tensor:
        """BatchNorm (unless folded: the fast eval path) and ReLU of layer ``i`` -> a new tensor;
        with ``fresh`` (``pre`` is a temporary nobody else reads) and no gradient to record, the
        ReLU rectifies ``pre`` in place: the same values without allocating and writing another
        tensor. (Under autograd it stays out of place: in-place ops on the reshaped views cost
        the backward more than they save, 12 % of a P2B training step.)"""
        if not self.activated[i]:
            return pre
        if self.training or not self.fast_eval:
            shape = pre.shape
            pre = self.norms[i](pre.reshape(-1, shape[-1])).reshape(shape)
            fresh = True  # BatchNorm's output
        if fresh and not (pre.requires_grad and torch.is_grad_enabled()):
            return F.relu_(pre)
        return F.relu(pre)

    def forward_from(self, i: int, pre: torch.Tensor, *, fresh: bool = False) -> torch.Tensor:
        """Continue from the pre-activation of layer ``i`` (its ``linear_params`` applied;
        ``fresh``: see :meth:`finish`)."""
        return self.hidden_from(i, pre, len(self.linears), fresh=fresh)

    def hidden_from(
        self, i: int, pre: torch.Tensor, stop: int, *, fresh: bool = False
    ) -> torch.Tensor:
        """From the pre-activation of layer ``i`` to the input of layer ``stop > i``
        (``fresh``: see :meth:`finish`)."""
        x = self.finish(i, pre, fresh=fresh)
        for j in range(i + 1, stop):
            w, b = self.linear_params(j)
            x = self.finish(j, F.linear(x, w, b), fresh=True)
        return x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w, b = self.linear_params(0)
        return self.forward_from(0, F.linear(x, w, b), fresh=True)


def dense_max(
    mlp: MLP,
    pre: torch.Tensor,
    dim: int,
    pool: Callable[[torch.Tensor, int], torch.Tensor] = max_pool,
) -> torch.Tensor:
    """``pool(mlp.forward_from(0, pre), dim)`` for neighbourhoods laid out densely (``pre``: the
    first layer's pre-activation, e.g. ``(B, M, k, C1)``, a temporary that the ReLU may
    overwrite); the MLP must end in a ReLU. ``pool`` is the training path's max
    (:func:`max_pool`, or ``torch.amax`` for its even split of the gradient among ties). In eval
    (fast path) the last Linear's bias and the ReLU act after the max, on one row per group
    instead of ``k`` (monotone: the same maxima up to the rounding of the bias add)."""
    last = len(mlp.linears) - 1
    if mlp.training or not mlp.fast_eval or last == 0:
        return pool(mlp.forward_from(0, pre, fresh=True), dim)
    w, bias = mlp.linear_params(last)
    out = F.linear(mlp.hidden_from(0, pre, last, fresh=True), w).amax(dim=dim)
    return mlp.finish(last, out if bias is None else out + bias, fresh=True)


def grouped_max(
    mlp: MLP,
    per_point: torch.Tensor,
    per_centre: torch.Tensor,
    group: torch.Tensor,
    point: torch.Tensor,
) -> torch.Tensor:
    """``max_j mlp.forward_from(0, per_point_j - per_centre_i)`` over the members ``j`` of each
    group ``i``: ``per_point (B, N, C1)``, ``per_centre (B, M, C1)``, pairs ``group (P,)`` (flat
    index ``b * M + m``, every group present) and ``point (P,)`` (flat ``b * N + j``, as
    :func:`trackers.ops.ball_query_pairs` gives) -> ``(B, M, C)``; the MLP must end in a ReLU.

    A ball query pads its slots with copies of the first hit, which cannot change a max: over the
    real hits only, the same values as the dense ``(B, M, k, C1)`` evaluation with less work
    (in training BatchNorm statistics would differ, so callers use it in eval unless asked).
    """
    b, m, c1 = per_centre.shape
    plain = mlp.training or not mlp.fast_eval
    # index_select, not [...]: its backward is several times faster on CPU (see ops.gather)
    pre = per_point.reshape(-1, c1).index_select(0, point) - per_centre.reshape(
        -1, c1
    ).index_select(0, group)
    last = len(mlp.linears) - 1
    bias = None
    if plain:  # BatchNorm on batch statistics (training), or unfolded: every member's output
        h = mlp.forward_from(0, pre, fresh=True)  # (P, C)
    elif last == 0:
        h = pre
    else:  # eval: the last bias and ReLU are monotone, so they go after the max (M rows, not
        # P): max_j relu(x_j + b) = relu(max_j x_j + b), bit for bit (rounding is monotone too)
        w, bias = mlp.linear_params(last)
        h = F.linear(mlp.hidden_from(0, pre, last, fresh=True), w)
    out = h.new_full((b * m, h.shape[-1]), -torch.inf)  # every group has a member
    out.scatter_reduce_(0, group[:, None].expand(-1, h.shape[-1]), h, "amax")
    if plain:
        return out.view(b, m, -1)
    if bias is not None:
        out = out + bias
    return mlp.finish(last, out, fresh=True).view(b, m, -1)
