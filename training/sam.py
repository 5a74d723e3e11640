"""Sharpness-Aware Minimization (Foret et al., ICLR 2021): the "-S" comparison of Tian et al. (TIP
2024).

SAM minimises ``max_{||e|| <= rho} L(w + e)``. With the first-order solution
``e(w) = rho * g / ||g||`` (``g = grad L(w)``, ``||.||`` the L2 norm over all parameters) one
update is:

1. compute ``g`` at ``w`` (the caller's first backward);
2. :meth:`SAM.first_step`: move to ``w + e(w)``;
3. compute the gradient at ``w + e(w)`` (the caller's second forward/backward);
4. :meth:`SAM.second_step`: go back to ``w`` and let the base optimizer step with that gradient.

:meth:`SAM.step` does 2-4 given a closure that recomputes the loss and calls ``backward``.
The wrapper keeps the base optimizer (Adam here) as is, so learning-rate schedulers attach to
``sam.base`` and ``state_dict`` is the base optimizer's.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["SAM"]


class SAM:
    """Wraps ``base`` (a ``torch.optim.Optimizer`` already built over the parameters)."""

    def __init__(self, base: torch.optim.Optimizer, rho: float = 0.05, eps: float = 1e-12) -> None:
        if rho < 0:
            raise ValueError(f"SAM rho must be non-negative, got {rho}")
        self.base = base
        self.rho = rho
        self.eps = eps
        self._perturbation: list[tuple[torch.Tensor, torch.Tensor]] = []

    @property
    def param_groups(self) -> list[dict]:
        return self.base.param_groups

    def _params_with_grad(self) -> list[torch.Tensor]:
        return [p for g in self.base.param_groups for p in g["params"] if p.grad is not None]

    @torch.no_grad()
    def grad_norm(self) -> torch.Tensor:
        params = self._params_with_grad()
        if not params:
            return torch.zeros(())
        return torch.linalg.vector_norm(
            torch.stack([torch.linalg.vector_norm(p.grad.detach(), 2) for p in params]), 2
        )

    @torch.no_grad()
    def first_step(self, zero_grad: bool = True) -> None:
        """Climb to ``w + rho * g / ||g||`` (uses the gradients currently in ``.grad``)."""
        if self._perturbation:
            raise RuntimeError("SAM.first_step called twice without second_step")
        scale = self.rho / (self.grad_norm() + self.eps)
        for p in self._params_with_grad():
            e = p.grad * scale.to(p.grad)
            p.add_(e)
            self._perturbation.append((p, e))
        if zero_grad:
            self.zero_grad()

    @torch.no_grad()
    def second_step(self, zero_grad: bool = True) -> None:
        """Return to ``w`` and take the base optimizer's step with the gradient at ``w + e``."""
        for p, e in self._perturbation:
            p.sub_(e)
        self._perturbation = []
        self.base.step()
        if zero_grad:
            self.zero_grad()

    def step(self, closure: Callable[[], torch.Tensor]) -> torch.Tensor:
        """Full SAM update; the gradients at ``w`` must already be in ``.grad``. ``closure``
        must recompute the loss at the perturbed weights, call ``backward`` and return it."""
        self.first_step(zero_grad=True)
        with torch.enable_grad():
            loss = closure()
        self.second_step(zero_grad=False)
        return loss

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.base.zero_grad(set_to_none=set_to_none)

    def state_dict(self) -> dict:
        return self.base.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.base.load_state_dict(state)
