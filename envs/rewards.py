"""Named, picklable rewards of the tracking env, and a registry for one's own.

A reward is a callable ``reward(pred, gt, prev_pred, step, info) -> float``:

- ``pred (7,)`` float64: the box the action produced (frame ``info["frame"]``);
- ``gt (7,)`` float64: that frame's ground-truth box;
- ``prev_pred (7,)`` float64: the previous prediction (the given box at the first step);
- ``step``: the step's index in the episode (0 for the first step);
- ``info``: the step's info, read-only (``iou``, ``center_error``, ``frame``, ``category``,
  ``observed``, ``tracklet``, ``target_points``, ...; see :class:`envs.tracking_env.TrackingEnv`).

The arrays are the callee's own copies. Built in (:func:`available_rewards`): ``iou_3d`` (the
oriented 3D IoU, ``info["iou"]``), ``iou_bev`` (bird's-eye IoU), ``neg_center_error`` (minus
the centre distance, m), ``iou_delta`` (IoU gain over keeping the previous box: ``IoU(pred, gt)
- IoU(prev_pred, gt)``), ``success`` (1 when the IoU reaches ``threshold``, default 0.5, else
0). Register one's own with :func:`register_reward`; the env takes a name (``reward="success"``,
``reward_kwargs={"threshold": 0.7}``) or any such callable. Rewards a vector env sends to
subprocesses must be picklable: module-level functions or instances of module-level classes.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from envs.geometry import iou_bev, iou_pair

__all__ = [
    "ROUND_OFF",
    "CenterError",
    "IoU3D",
    "IoUBEV",
    "IoUDelta",
    "RewardFn",
    "Success",
    "available_rewards",
    "check_reward",
    "make_reward",
    "register_reward",
    "snap_iou",
]

ROUND_OFF = 1e-9
"""IoUs above ``1 - ROUND_OFF`` are reported as 1 and centre errors below it (metres) as 0: the
exact ground-truth offset reproduces the ground-truth box only up to float round-off (~1e-15),
and OPE's last Success threshold (IoU >= 1) and first Precision threshold (error <= 0) are exact.
"""


class RewardFn(Protocol):
    """``(pred (7,), gt (7,), prev_pred (7,), step, info) -> float``; see the module docstring."""

    def __call__(
        self,
        pred: np.ndarray,
        gt: np.ndarray,
        prev_pred: np.ndarray,
        step: int,
        info: Mapping[str, Any],
    ) -> float: ...


def snap_iou(iou: float) -> float:
    """IoUs within :data:`ROUND_OFF` of 1 are round-off of the polygon clipping: report 1."""
    return 1.0 if iou > 1.0 - ROUND_OFF else iou


@dataclass(frozen=True)
class IoU3D:
    """The oriented 3D IoU of the prediction with the ground truth (``info["iou"]``)."""

    def __call__(self, pred, gt, prev_pred, step, info) -> float:
        return info["iou"]


@dataclass(frozen=True)
class IoUBEV:
    """The bird's-eye-view IoU of the prediction with the ground truth."""

    def __call__(self, pred, gt, prev_pred, step, info) -> float:
        return snap_iou(float(iou_bev(pred, gt)))


@dataclass(frozen=True)
class CenterError:
    """Minus the centre distance of the prediction to the ground truth (m)."""

    def __call__(self, pred, gt, prev_pred, step, info) -> float:
        return -info["center_error"]


@dataclass(frozen=True)
class IoUDelta:
    """The 3D IoU gain of the prediction over keeping the previous prediction for this frame:
    positive when the action moved the box towards the target."""

    def __call__(self, pred, gt, prev_pred, step, info) -> float:
        kept = snap_iou(iou_pair(prev_pred.tolist(), gt.tolist()))
        return info["iou"] - kept


@dataclass(frozen=True)
class Success:
    """1 when the 3D IoU reaches ``threshold`` (OPE's success at one threshold), else 0."""

    threshold: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError(f"success reward: threshold must be in [0, 1]; got {self.threshold}")

    def __call__(self, pred, gt, prev_pred, step, info) -> float:
        return 1.0 if info["iou"] >= self.threshold else 0.0


RewardFactory = Callable[..., RewardFn]

_REGISTRY: dict[str, RewardFactory] = {
    "iou_3d": IoU3D,
    "iou_bev": IoUBEV,
    "neg_center_error": CenterError,
    "iou_delta": IoUDelta,
    "success": Success,
}


def available_rewards() -> tuple[str, ...]:
    """Names :func:`make_reward` knows, built-in first."""
    return tuple(_REGISTRY)


def register_reward(
    name: str, factory: RewardFactory | None = None, *, overwrite: bool = False
) -> Any:
    """Register ``factory`` (called with the env's ``reward_kwargs``, returns a reward) under
    ``name``; without ``factory``, a decorator. A taken name raises ``ValueError`` unless
    ``overwrite``. A class whose instances are rewards is a factory::

        @register_reward("close")
        @dataclass(frozen=True)
        class Close:
            radius_m: float = 1.0
            def __call__(self, pred, gt, prev_pred, step, info):
                return float(info["center_error"] <= self.radius_m)
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"reward name must be a non-empty string; got {name!r}")

    def add(f: RewardFactory) -> RewardFactory:
        if not callable(f):
            raise TypeError(f"reward factory for {name!r} must be callable; got {f!r}")
        if name in _REGISTRY and not overwrite:
            raise ValueError(f"reward {name!r} is already registered (pass overwrite=True)")
        _REGISTRY[name] = f
        return f

    return add if factory is None else add(factory)


def make_reward(name: str, **kwargs: Any) -> RewardFn:
    """The registered reward ``name`` built with ``kwargs``; ``ValueError`` naming the valid
    names for an unknown one."""
    if name not in _REGISTRY:
        raise ValueError(
            f"unknown reward {name!r}; valid: {', '.join(map(repr, available_rewards()))}"
        )
    try:
        return check_reward(_REGISTRY[name](**kwargs))
    except TypeError as exc:
        raise TypeError(f"reward {name!r} with reward_kwargs={kwargs}: {exc}") from None


def check_reward(reward: Any) -> RewardFn:
    """``reward`` itself if it is a callable taking ``(pred, gt, prev_pred, step, info)``,
    else a ``TypeError`` saying what is expected (e.g. a reward of the old ``(pred, gt)``
    signature)."""
    if not callable(reward):
        raise TypeError(f"a reward must be callable; got {reward!r}")
    try:
        signature = inspect.signature(reward)
    except (TypeError, ValueError):  # no signature to check (some builtins): trust it
        return reward
    try:
        signature.bind(None, None, None, 0, {})
    except TypeError:
        raise TypeError(
            f"reward {reward!r} must accept (pred, gt, prev_pred, step, info); its signature "
            f"is {signature}"
        ) from None
    return reward


def finite_reward(value: Any, reward: RewardFn) -> float:
    """``float(value)``, or a ``ValueError`` naming ``reward`` when it is not finite."""
    out = float(value)
    if not math.isfinite(out):
        raise ValueError(f"the reward {reward!r} returned {out}")
    return out
