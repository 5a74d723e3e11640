"""P2B's exact eval speed-up: the TFA max over template seeds by piecewise-linear interpolation.

For a template seed ``i`` the first-layer pre-activation of the pair ``(i, j)`` is ``a_i + c w``
and depends on the pair only through the scalar ``c = cos_ij``, so the TFA MLP output is
``F_i(c)``, a continuous piecewise-linear function of ``c`` (Linear + ReLU layers, BatchNorm folded
in eval). :func:`knots` finds all its breakpoints in ``[min_j c_ij, max_j c_ij]`` exactly, layer
by layer: between consecutive known knots a layer's pre-activation is affine, so each sign change
between two knots is one kink, located by linear interpolation. The last layer's pre-activation
is evaluated at the knots only, interpolated linearly at every ``c_ij`` (one small ``bmm``,
:func:`interpolate_max`), and the final ReLU applied after the max over ``i``
(``max_i relu = relu max_i``). The shipped P2B checkpoints have a handful of knots per template
seed on env observations (mean 3-5, at most 16; random init: 2-4), against 128 search seeds: the
same function (to float rounding) with a fraction of the work. When knots are too many
(:data:`MAX_KNOT_FRACTION`) :func:`tfa_pre_max` returns ``None`` and the caller evaluates every
pair. :func:`unique_seeds` drops repeated template seeds first (copies of padded input points):
the max over template seeds is the same.

:class:`trackers.p2b.P2BFusion` uses this module on its fast eval path only.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from trackers import ops
from trackers.layers import MLP

__all__ = [
    "MAX_KNOT_FRACTION",
    "interpolate_max",
    "knots",
    "pre_activation",
    "tfa_pre_max",
    "unique_seeds",
]

#: Knots per template seed (a fraction of the search seeds) above which the dense path is cheaper.
MAX_KNOT_FRACTION = 0.25
#: Floats in one interpolated block (1 MiB): small enough to stay in cache for the running max.
_CACHE_FLOATS = 1 << 18


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


def pre_activation(
    mlp: MLP, a: torch.Tensor, w: torch.Tensor, c: torch.Tensor, layer: int
) -> torch.Tensor:
    """Pre-activation of ``layer`` for scalar inputs: ``a (B, M, H)``, ``w (H,)``, ``c (B, M, K)``
    -> ``(B, M, K, C)``, the MLP applied to the first-layer pre-activations ``a + c w``."""
    x = torch.addcmul(a[:, :, None, :], c[..., None], w)
    for i in range(1, layer + 1):
        wi, bi = mlp.linear_params(i)
        x = F.linear(mlp.finish(i - 1, x, fresh=True), wi, bi)
    return x


def knots(
    mlp: MLP, a: torch.Tensor, w: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, max_knots: int
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Breakpoints of ``c -> mlp`` (eval: Linear + ReLU layers) with first-layer pre-activation
    ``a + c w`` on ``[lo, hi]``: ``a (B, M, H)``, ``w (H,)``, ``lo, hi (B, M)`` -> sorted knots
    ``(B, M, K)`` (from ``lo`` to ``hi``; rows with fewer knots repeat ``hi``) and the last
    layer's pre-activation at them ``(B, M, K, C)``; None when a row needs more than
    ``max_knots`` knots (then evaluating at the knots saves nothing).
    """
    t = torch.stack([lo, hi], dim=-1)  # (B, M, K)
    for layer in range(len(mlp.linears) - 1):
        pre = pre_activation(mlp, a, w, t, layer)  # (B, M, K, C): affine between knots
        p0, p1 = pre[:, :, :-1], pre[:, :, 1:]
        cross = (p0 > 0) != (p1 > 0)  # (B, M, K - 1, C): one zero of the ReLU input inside
        new = int(cross.flatten(2).sum(-1).max())
        if t.shape[-1] + new > max_knots:
            return None
        if new == 0:
            continue
        t0, t1 = t[:, :, :-1, None], t[:, :, 1:, None]
        # p0 / (p0 - p1) is in [0, 1] where the signs differ: a well-conditioned interpolation
        zero = torch.addcmul(t0, t1 - t0, p0 / torch.where(cross, p0 - p1, 1.0))
        zero = torch.minimum(zero, t1)  # rounding must not move a kink past its interval
        zero = torch.where(cross, zero, hi[:, :, None, None])  # padding: repeats of hi
        t = torch.cat([t, zero.flatten(2)], dim=-1)
        t = t.topk(
            t.shape[-1] - zero.shape[2] * zero.shape[3] + new, dim=-1, largest=False, sorted=True
        ).values
    return t, pre_activation(mlp, a, w, t, len(mlp.linears) - 1)


def interpolate_max(t: torch.Tensor, values: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Max over ``M`` of a piecewise-linear interpolation: knots ``t (B, M, K)`` (sorted),
    ``values (B, M, K, C)`` at them, queries ``c (B, M, N)`` within ``[t_0, t_K-1]`` ->
    ``max_m f_m(c_mn)``, ``(B, N, C)``.

    Each interpolation is a ``bmm`` with an ``(N, K)`` matrix holding ``1 - lambda`` and
    ``lambda`` at the two enclosing knots (cheaper than gathering two ``C``-rows per query), done
    for a few ``m`` at a time: the ``(chunk, N, C)`` block stays in cache for the running max.
    """
    b, m, k = t.shape
    q = (torch.searchsorted(t, c.contiguous(), right=True) - 1).clamp_(0, k - 2)  # (B, M, N)
    t0, t1 = t.gather(2, q), t.gather(2, q + 1)
    span = t1 - t0
    lam = torch.where(span > 0, (c - t0) / torch.where(span > 0, span, 1.0), 0.0).clamp_(0, 1)
    coef = c.new_zeros(b, m, c.shape[2], k)
    coef.scatter_(3, q[..., None], (1 - lam)[..., None])
    coef.scatter_(3, q[..., None] + 1, lam[..., None])
    chunk = max(1, _CACHE_FLOATS // (b * c.shape[2] * values.shape[-1]))
    out = None
    for s in range(0, m, chunk):
        part = torch.matmul(coef[:, s : s + chunk], values[:, s : s + chunk]).amax(dim=1)
        if out is None:
            out = part
        elif torch.is_grad_enabled():  # out= has no autograd
            out = torch.maximum(out, part)
        else:  # the running max in place: no allocation per chunk
            out = torch.maximum(out, part, out=out)
    return out


def tfa_pre_max(
    mlp: MLP, a: torch.Tensor, w: torch.Tensor, cos: torch.Tensor
) -> torch.Tensor | None:
    """``max_i`` of the last pre-activation of ``mlp`` over template seeds: first-layer template
    part ``a (B, M_T, H)``, similarity weight ``w (H,)``, similarities ``cos (B, M_T, M_S)`` ->
    ``(B, M_S, C)`` (the final ReLU not applied), or ``None`` when some template seed has more
    than ``MAX_KNOT_FRACTION * M_S`` knots (then evaluating every pair is cheaper)."""
    max_knots = max(2, int(MAX_KNOT_FRACTION * cos.shape[2]))
    found = knots(mlp, a, w, cos.amin(dim=2), cos.amax(dim=2), max_knots)
    if found is None:
        return None
    return interpolate_max(found[0], found[1], cos)
