"""Feature-decorrelation weights (training.weighting) and SAM (training.sam)."""

from __future__ import annotations

import math

import torch

from training.sam import SAM
from training.weighting import (
    FeatureDecorrelation,
    _standardize,
    decorrelation_objective,
    draw_rff,
    rff,
)


def _spurious_features(b: int = 48, d: int = 16, frac: float = 0.75, seed: int = 0):
    """Most samples share one latent factor across all channels (a spurious correlation); the
    rest have independent channels."""
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, d, generator=g)
    m = int(frac * b)
    z[:m] = torch.randn(m, 1, generator=g) + 0.3 * torch.randn(m, d, generator=g)
    return z, m


def test_vectorised_objective_matches_pairwise_loop():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(12, 7, generator=g)
    w = torch.softmax(torch.randn(12, generator=g), 0)
    p = draw_rff(7, 5, g)
    fast = decorrelation_objective(x, w, p)
    xs = _standardize(x)
    u, v = rff(xs, p.a_u, p.b_u), rff(xs, p.a_v, p.b_v)
    u = u - (w[:, None, None] * u).sum(0)
    v = v - (w[:, None, None] * v).sum(0)
    slow = 0.0
    for i in range(7):
        for j in range(i + 1, 7):
            lam = (w[:, None] * u[:, i]).T @ v[:, j]  # (5, 5) weighted cross-covariance
            slow += float((lam**2).sum())
    assert math.isclose(float(fast), slow, rel_tol=1e-4)


def test_learned_weights_decorrelate_spurious_features():
    z, m = _spurious_features()
    fd = FeatureDecorrelation(seed=0)
    w = fd.weights(z, step=0)
    assert w.shape == (48,)
    assert (w >= 0).all()
    assert math.isclose(float(w.sum()), 1.0, rel_tol=1e-5)
    uniform, learned = fd.last_objective
    assert learned < 0.5 * uniform  # well below uniform weights
    # the majority carrying the spurious correlation is down-weighted
    assert float(w[:m].sum()) < 0.85 * m / 48
    # an independent evaluation with fresh random functions agrees
    p = draw_rff(16, 5, torch.Generator().manual_seed(99))
    ones = torch.full((48,), 1 / 48)
    learned_obj = float(decorrelation_objective(z, w, p))
    assert learned_obj < 0.6 * float(decorrelation_objective(z, ones, p))


def test_memory_roundtrip_and_determinism():
    z, _ = _spurious_features(b=16, d=8)
    a = FeatureDecorrelation(seed=3)
    a.weights(z, 0)
    state = a.state_dict()
    b = FeatureDecorrelation(seed=3)
    b.load_state_dict(state)
    wa, wb = a.weights(z * 1.1, 1), b.weights(z * 1.1, 1)
    assert torch.equal(wa, wb)
    assert a.memory_features.shape == (16, 8)
    # pooled (B, M, D) input accepted
    w3 = FeatureDecorrelation(seed=3).weights(z[:, None].expand(-1, 4, -1), 0)
    assert torch.allclose(w3, FeatureDecorrelation(seed=3).weights(z, 0))


def test_sam_step_on_quadratic_matches_hand_computation():
    a = torch.tensor([[2.0, 0.5], [0.5, 1.0]])
    w = torch.nn.Parameter(torch.tensor([1.0, -2.0]))
    lr, rho = 0.1, 0.05
    sam = SAM(torch.optim.SGD([w], lr=lr), rho=rho)

    def loss_fn():
        return 0.5 * w @ a @ w

    loss_fn().backward()

    def closure():
        loss = loss_fn()
        loss.backward()
        return loss

    sam.step(closure)
    w0 = torch.tensor([1.0, -2.0])
    g = a @ w0
    e = rho * g / g.norm()
    g_adv = a @ (w0 + e)
    expected = w0 - lr * g_adv
    assert torch.allclose(w.detach(), expected, atol=1e-6)
