"""An exponential moving average (EMA) of a model's weights: the trainer's ``ema_decay`` option.

With the small batches of CPU training the weights after any one step are noisy: the val Success
of one run moves by about 5 points between neighbouring epochs. Averaging the weights along the
trajectory is meant to smooth that out, and weight averages tend to sit in flatter minima that
generalise better to shifted test distributions (SWA, Izmailov et al., UAI 2018; SWAD, Cha et
al., NeurIPS 2021, for domain generalisation). Measured here once
(docs/notes/checkpoints-history.md): on one BAT-U run the average did not beat the raw final
weights. The trainer validates, keeps and
exports the averaged weights; the optimiser keeps stepping the raw ones.

Every floating-point entry of the state dict (parameters and BatchNorm running statistics) is
averaged; integer buffers (``num_batches_tracked``) are copied. The decay warms up as
``min(decay, (1 + n) / (10 + n))`` after ``n`` updates, so the first steps, far from where the
run ends, fade out quickly instead of lingering for ``1 / (1 - decay)`` steps.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["WeightEMA"]


class WeightEMA:
    """``shadow <- d * shadow + (1 - d) * weights`` after every optimiser step.

    ``decay`` in ``(0, 1)``; ``shadow`` starts as a copy of ``model``'s state dict.
    """

    def __init__(self, model: torch.nn.Module, decay: float) -> None:
        if not 0 < decay < 1:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.updates = 0
        self.shadow = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def current_decay(self) -> float:
        """The decay the next update uses (warm-up included)."""
        n = self.updates + 1
        return min(self.decay, (1 + n) / (10 + n))

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        d = self.current_decay()
        for key, value in model.state_dict().items():
            shadow = self.shadow[key]
            if shadow.is_floating_point():
                shadow.mul_(d).add_(value.detach(), alpha=1 - d)
            else:
                shadow.copy_(value)
        self.updates += 1

    def copy_to(self, model: torch.nn.Module) -> torch.nn.Module:
        """Load the averaged weights into ``model`` (same architecture) and return it."""
        model.load_state_dict(self.shadow)
        return model

    def state_dict(self) -> dict[str, Any]:
        return {
            "decay": self.decay,
            "updates": self.updates,
            "shadow": {k: v.clone() for k, v in self.shadow.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if set(state["shadow"]) != set(self.shadow):
            raise ValueError("the saved weight average holds other parameters than this model")
        self.decay = float(state["decay"])
        self.updates = int(state["updates"])
        for key, value in state["shadow"].items():
            self.shadow[key].copy_(value)
