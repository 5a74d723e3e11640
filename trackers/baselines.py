"""Non-learned baselines with the tracker interface ``act(obs) -> action``.

Both are stateless (the env's ``motion`` observation carries the last predicted motion), accept
one observation (dict of ``(512, 3)`` / ``(1024, 3)`` / ``(3,)`` / ``(4,)`` arrays) or a batch
(the same keys with a leading ``B``), numpy or torch, and return numpy float32 ``(4,)`` or
``(B, 4)`` offsets ``(dx, dy, dz, dyaw)`` in the reference box frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from trackers.registry import register

__all__ = ["BASELINES", "ConstantVelocity", "PreviousBox"]


def _as_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def _motion(obs: Mapping[str, Any]) -> np.ndarray:
    if "motion" not in obs:
        raise KeyError(f"observation has no 'motion' key; keys: {sorted(obs)}")
    motion = _as_numpy(obs["motion"])
    if motion.shape[-1] != 4 or motion.ndim not in (1, 2):
        raise ValueError(f"obs['motion'] must have shape (4,) or (B, 4); got {motion.shape}")
    return motion


@register("previous_box")
class PreviousBox:
    """Keep the previous box: the zero offset (with ``reference="prediction"`` the box stays)."""

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        """``obs`` single or batched -> zeros ``(4,)`` or ``(B, 4)`` float32."""
        return np.zeros_like(_motion(obs))

    def __repr__(self) -> str:
        return "PreviousBox()"


@register("constant_velocity")
class ConstantVelocity:
    """Repeat the last predicted motion ``obs["motion"]``.

    The motion is zero at the first step (only frame 0's box is known), so with the default
    ``init="zero"`` (the plain rule) the predictions of this baseline alone never move and it
    scores exactly like :class:`PreviousBox`. With ``init="points"``, whenever ``obs["motion"]``
    is exactly zero the motion is estimated from the points instead (a crude, clutter-sensitive
    heuristic): two mean-shift iterations of the centroid of the search points inside the
    target box, ignoring its lowest ``ground_m`` metres (the ground), minus the same centroid
    of the first-frame template half; ``dz = dyaw = 0``; zero when either set has fewer than
    ``min_points`` distinct points or the shift exceeds half the box length.
    """

    def __init__(
        self, init: str = "zero", ground_m: float = 0.3, iterations: int = 2, min_points: int = 20
    ) -> None:
        if init not in ("points", "zero"):
            raise ValueError(f"unknown init {init!r}; valid: 'points', 'zero'")
        self.init = init
        self.ground_m = float(ground_m)
        self.iterations = int(iterations)
        self.min_points = int(min_points)

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        """``obs`` single or batched -> float32 ``(4,)`` or ``(B, 4)`` offsets."""
        motion = _motion(obs).copy()
        if self.init == "zero":
            return motion
        batched = motion.ndim == 2
        m = motion if batched else motion[None]
        still = ~np.any(m != 0, axis=1)
        if still.any():
            search = _as_numpy(obs["search"]).reshape(len(m), -1, 3)
            template = _as_numpy(obs["template"]).reshape(len(m), -1, 3)
            size = _as_numpy(obs["size"]).reshape(len(m), 3)
            for b in np.flatnonzero(still):
                m[b, :2] = self._estimate(search[b], template[b], size[b])
        return m if batched else m[0]

    def _select(self, points: np.ndarray, centre: np.ndarray, size: np.ndarray) -> np.ndarray:
        rel = points[:, :2] - centre
        keep = (np.abs(rel[:, 0]) <= 0.5 * size[0]) & (np.abs(rel[:, 1]) <= 0.5 * size[1])
        keep &= points[:, 2] > -0.5 * size[2] + self.ground_m
        keep &= points[:, 2] <= 0.5 * size[2]
        keep &= np.any(points != 0, axis=1)  # zero rows pad empty point sets
        return points[keep, :2]

    def _estimate(self, search: np.ndarray, template: np.ndarray, size: np.ndarray) -> np.ndarray:
        zero = np.zeros(2, np.float32)
        first = self._select(template[: len(template) // 2], zero, size)
        if len(np.unique(first, axis=0)) < self.min_points:
            return zero
        bias = first.mean(axis=0)  # where the visible surface sits in the box frame
        centre = zero
        for _ in range(self.iterations):
            sel = self._select(search, centre, size)
            if len(np.unique(sel, axis=0)) < self.min_points:
                return zero
            centre = (sel.mean(axis=0) - bias).astype(np.float32)
        # trust only a shift the target could make in one frame (half its length)
        return centre if np.hypot(*centre) <= 0.5 * size[0] else zero

    def __repr__(self) -> str:
        return f"ConstantVelocity(init={self.init!r})"


BASELINES = {"previous_box": PreviousBox, "constant_velocity": ConstantVelocity}
