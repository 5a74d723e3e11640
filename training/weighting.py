"""Feature-decorrelation sample weighting (the "-W" trainer of Tian et al. (TIP 2024) Sec. III-C).

What the paper specifies (Algorithm 1, Eq. 2-7), and how it is done here:

* ``Z' = tau(Z)``: the fused search features ``Z (B, M_S, D)`` averaged over the search seeds,
  ``(B, D)`` (:func:`pool_features`), detached from the network.
* Random Fourier Features (Eq. 7): ``N_u = N_v = 5`` functions ``sqrt(2) cos(a x + b)`` with
  ``a ~ N(0, 1)``, ``b ~ U(0, 2 pi)``; one set ``u`` for the first and an independent set ``v`` for
  the second variable of each pair. They are drawn per channel and redrawn at every call (as
  StableNet does), from a ``torch.Generator`` seeded by ``(seed, step)`` so a resumed run draws
  the same functions.
* Weighted partial cross-covariance of every channel pair ``i < j`` (Eq. 2) and the sum of their
  squared Frobenius norms (Eq. 3). Eq. 2 as printed multiplies the features by weights that sum to
  1 and subtracts an un-normalised mean, which is not scale-consistent (and its minimiser runs
  away); we use the weighted cross-covariance that StableNet's reference implementation computes,
  with ``w`` summing to 1: ``Lambda_ij = sum_m w_m (u(Z'_mi) - u_bar_i)^T (v(Z'_mj) - v_bar_j)``,
  ``u_bar_i = sum_k w_k u(Z'_ki)`` — for uniform weights the ordinary (biased) sample
  cross-covariance.
* Vectorised: with the RFF of all rows ``U, V (n, D N_u)`` (computed once per call — they do
  not depend on the weights), every block is in ``Lambda = U^T diag(w) V - (U^T w)(V^T w)^T``,
  one ``(D N_u, D N_v)`` matrix; the squared Frobenius norms of its blocks are a reshape-and-sum
  to ``(D, D)``, and Eq. 3 is the sum of the strict upper triangle — no Python loop over the
  ``D^2`` pairs.
* The weights are found by SGD for 20 iterations at lr 1.0, decayed x0.1 after 10 (Eq. 4), on
  detached ``Z'``; the network then steps on ``sum_m w_m L_m`` (Eq. 5); the two alternate every
  iteration (Algorithm 1) — the trainer (:mod:`training.pretrain`) does the alternation.

Where the paper is silent we follow StableNet, and say so here:

* Weights are parametrised by logits through a softmax (non-negative, summing to 1 by
  construction), initialised uniform; the SGD has momentum 0.9.
* A memory of earlier batches: ``memory_size`` rows of pooled features and their learned logits
  (StableNet's "global" pre-saved features), joined to the current batch when the objective is
  computed (the memory's logits are fixed during the inner loop), updated after every call — a
  running mean for the first 10 calls, then an exponential moving average with ratio 0.9. The
  returned weights are the softmax over the current batch's logits only (they sum to 1 over B).
* StableNet's concentration penalty ``sum w^2`` keeps the weights from collapsing onto one sample
  (a single sample has zero covariance, the trivial minimiser of Eq. 3).
* Our scaling choices: the inner objective is Eq. 3 divided by its value at uniform weights, plus
  ``penalty * B * sum w^2`` (1 at uniform weights; default ``penalty=0.1``), so the step size of
  the inner SGD (lr 1.0 as in the paper) does not depend on the feature dimension or scale. The
  pooled features are standardised per channel (over the rows of the objective, unweighted)
  before the RFF, so that ``a ~ N(0, 1)`` sees unit-scale inputs whatever the network's feature
  scale (``standardize=False`` gives the literal Eq. 7 on raw features).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "FeatureDecorrelation",
    "decorrelation_objective",
    "draw_rff",
    "effective_sample_size",
    "objective_from_rff",
    "pool_features",
    "rff",
    "rff_features",
]


def pool_features(z: torch.Tensor) -> torch.Tensor:
    """``tau`` of the paper: average pooling of fused features ``(B, M_S, D)`` -> ``(B, D)``."""
    if z.dim() == 2:
        return z
    if z.dim() != 3:
        raise ValueError(f"fused features must be (B, M_S, D) or (B, D), got {tuple(z.shape)}")
    return z.mean(dim=1)


@dataclass
class RFFParams:
    """Random Fourier functions of one call: ``a``, ``b`` of ``u`` and ``v``, each ``(D, K)``."""

    a_u: torch.Tensor
    b_u: torch.Tensor
    a_v: torch.Tensor
    b_v: torch.Tensor


def draw_rff(
    dim: int, n_functions: int, generator: torch.Generator, dtype=torch.float32
) -> RFFParams:
    """Draw ``u`` and ``v`` (Eq. 7): per channel ``n_functions`` frequencies ``a ~ N(0, 1)`` and
    phases ``b ~ U(0, 2 pi)``."""

    def one() -> tuple[torch.Tensor, torch.Tensor]:
        a = torch.randn(dim, n_functions, generator=generator, dtype=dtype)
        b = torch.rand(dim, n_functions, generator=generator, dtype=dtype) * (2.0 * math.pi)
        return a, b

    a_u, b_u = one()
    a_v, b_v = one()
    return RFFParams(a_u, b_u, a_v, b_v)


def rff(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``sqrt(2) cos(a x + b)`` per channel: ``x (n, D)``, ``a, b (D, K)`` -> ``(n, D, K)``."""
    return math.sqrt(2.0) * torch.cos(x[:, :, None] * a + b)


def _standardize(x: torch.Tensor) -> torch.Tensor:
    mean = x.mean(dim=0, keepdim=True)
    std = x.std(dim=0, keepdim=True, unbiased=False)
    return (x - mean) / torch.where(std > 1e-8, std, torch.ones_like(std))


def rff_features(
    features: torch.Tensor, params: RFFParams, *, standardize: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """``u(Z')`` and ``v(Z')`` of features ``(n, D)``, each flattened to ``(n, D * K)``; they do
    not depend on the weights, so the inner loop computes them once."""
    n = features.shape[0]
    x = _standardize(features) if standardize else features
    u = rff(x, params.a_u, params.b_u).reshape(n, -1)
    v = rff(x, params.a_v, params.b_v).reshape(n, -1)
    return u, v


def objective_from_rff(
    u: torch.Tensor, v: torch.Tensor, weights: torch.Tensor, d: int
) -> torch.Tensor:
    """Eq. 3 from precomputed RFF ``(n, D K)``: ``sum_{i<j} ||Lambda_ij||_F^2`` with
    ``Lambda = U^T diag(w) V - (U^T w)(V^T w)^T`` (the weighted cross-covariance)."""
    w = weights.to(u.dtype)
    u_bar = w @ u
    v_bar = w @ v
    cross = (u * w[:, None]).T @ v - torch.outer(u_bar, v_bar)  # every Lambda_ij, (D K, D K)
    k = u.shape[1] // d
    norms = (cross * cross).reshape(d, k, d, k).sum(dim=(1, 3))  # ||Lambda_ij||_F^2, (D, D)
    return torch.triu(norms, diagonal=1).sum()


def decorrelation_objective(
    features: torch.Tensor,
    weights: torch.Tensor,
    params: RFFParams,
    *,
    standardize: bool = True,
    normalize: bool = False,
) -> torch.Tensor:
    """Eq. 3: ``sum_{i<j} ||Lambda_ij(w)||_F^2`` of features ``(n, D)`` under weights ``(n,)``.

    ``weights`` (non-negative) should sum to 1. ``normalize=True`` divides by the number of
    pairs. Differentiable in ``weights``.
    """
    n, d = features.shape
    if n < 2:
        raise ValueError("the decorrelation objective needs at least 2 samples")
    u, v = rff_features(features, params, standardize=standardize)
    total = objective_from_rff(u, v, weights, d)
    if normalize:
        total = total / (d * (d - 1) / 2.0)
    return total


class FeatureDecorrelation:
    """Learns per-sample weights that decorrelate pooled fused features (see the module docstring).

    Call :meth:`weights` once per training iteration with the batch's detached features; it runs the
    inner SGD, updates the memory and returns ``(B,)`` weights (non-negative, summing to 1).
    :meth:`state_dict` / :meth:`load_state_dict` carry the memory through checkpoints.
    """

    def __init__(
        self,
        *,
        n_functions: int = 5,
        iterations: int = 20,
        lr: float = 1.0,
        decay_every: int = 10,
        decay: float = 0.1,
        momentum: float = 0.9,
        penalty: float = 0.1,
        memory_size: int | None = None,
        memory_ratio: float = 0.9,
        use_memory: bool = True,
        standardize: bool = True,
        seed: int = 0,
    ) -> None:
        if n_functions < 1 or iterations < 0 or lr <= 0 or not 0.0 <= memory_ratio < 1.0:
            raise ValueError("invalid decorrelation settings")
        self.n_functions = n_functions
        self.iterations = iterations
        self.lr = lr
        self.decay_every = decay_every
        self.decay = decay
        self.momentum = momentum
        self.penalty = penalty
        self.memory_size = memory_size
        self.memory_ratio = memory_ratio
        self.use_memory = use_memory
        self.standardize = standardize
        self.seed = seed
        self.memory_features: torch.Tensor | None = None
        self.memory_logits: torch.Tensor | None = None
        self.updates = 0
        self.last_objective: tuple[float, float] | None = None  # (uniform, learned) of last call

    # ------------------------------------------------------------------ the inner problem
    def _generator(self, step: int) -> torch.Generator:
        g = torch.Generator()
        g.manual_seed((self.seed * 1_000_003 + step * 7919 + 12345) % (2**63 - 1))
        return g

    @torch.no_grad()
    def _update_memory(self, feats: torch.Tensor, logits: torch.Tensor) -> None:
        if not self.use_memory:
            return
        if self.memory_features is None:
            size = self.memory_size or feats.shape[0]
            self.memory_features = torch.zeros(size, feats.shape[1], dtype=feats.dtype)
            self.memory_logits = torch.zeros(size, dtype=logits.dtype)
        k = min(feats.shape[0], self.memory_features.shape[0])
        if self.updates < 10:  # running mean of the first calls (StableNet's warm start)
            r = self.updates / (self.updates + 1.0)
        else:
            r = self.memory_ratio
        self.memory_features[:k] = r * self.memory_features[:k] + (1.0 - r) * feats[:k]
        self.memory_logits[:k] = r * self.memory_logits[:k] + (1.0 - r) * logits[:k]
        self.updates += 1

    def weights(self, features: torch.Tensor, step: int) -> torch.Tensor:
        """Learn weights for one batch of (detached) features ``(B, D)`` or ``(B, M_S, D)``."""
        feats = pool_features(features).detach().to(torch.float32).cpu()
        b = feats.shape[0]
        if b < 2:
            return torch.ones(b)
        params = draw_rff(feats.shape[1], self.n_functions, self._generator(step))
        if self.use_memory and self.memory_features is not None and self.updates > 0:
            mem_f, mem_l = self.memory_features, self.memory_logits
        else:
            mem_f, mem_l = feats[:0], torch.zeros(0)
        all_feats = torch.cat([feats, mem_f], dim=0)
        u, v = rff_features(all_feats, params, standardize=self.standardize)
        d = all_feats.shape[1]
        logits = torch.zeros(b, requires_grad=True)
        opt = torch.optim.SGD([logits], lr=self.lr, momentum=self.momentum)
        scale = 1.0

        def objective(lg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            w_all = torch.softmax(torch.cat([lg, mem_l]), dim=0)
            dec = objective_from_rff(u, v, w_all, d)
            w = torch.softmax(lg, dim=0)
            return dec, dec / scale + self.penalty * b * (w * w).sum()

        with torch.no_grad():
            uniform = float(objective(logits)[0])
        scale = max(uniform, 1e-12)
        for it in range(self.iterations):
            lr = self.lr * (self.decay ** (it // self.decay_every)) if self.decay_every else self.lr
            for group in opt.param_groups:
                group["lr"] = lr
            opt.zero_grad()
            _, total = objective(logits)
            total.backward()
            opt.step()
        with torch.no_grad():
            learned = float(objective(logits)[0])
            w = torch.softmax(logits.detach(), dim=0)
        self.last_objective = (uniform, learned)
        self._update_memory(feats, logits.detach())
        return w

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        state: dict = {"updates": torch.tensor(self.updates)}
        if self.memory_features is not None:
            state["memory_features"] = self.memory_features.clone()
            state["memory_logits"] = self.memory_logits.clone()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.updates = int(state.get("updates", 0))
        mf = state.get("memory_features")
        self.memory_features = None if mf is None else mf.clone()
        ml = state.get("memory_logits")
        self.memory_logits = None if ml is None else ml.clone()


def effective_sample_size(weights: torch.Tensor) -> float:
    """``1 / sum w^2`` for weights summing to 1 (B for uniform weights)."""
    return float(1.0 / (weights * weights).sum())
