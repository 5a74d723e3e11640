"""Any tracker by name or file: :func:`load_tracker`, what ``pointtrack eval``, ``select``,
``demo`` and ``finetune`` read their ``--tracker`` with; :func:`load_kernels`, the compiled
kernels such a command's set-up loads for it."""

from __future__ import annotations

from typing import Any

import torch

import trackers
from envs.kernels import load_kernels as load_env_kernels
from trackers import decision, ops
from trackers.registry import find_checkpoint
from training.checkpoint import is_training_checkpoint, tracker_from_checkpoint
from training.residual_file import is_residual_file

__all__ = ["UntrainedTrackerError", "load_kernels", "load_tracker"]


class UntrainedTrackerError(ValueError):
    """A learned tracker named without weights, loaded without ``untrained=True``."""


def load_tracker(name_or_path: str, *, untrained: bool = False, seed: int = 0) -> Any:
    """A tracker by name, tracker file, shipped checkpoint name or training checkpoint.

    * A ``pointtrack finetune --algo residual`` result (``residual.safetensors`` or its run
      directory) loads as a :class:`training.rl.wrappers.ResidualTracker`.
    * A training checkpoint (``RUN/best.pt``, ``RUN/last.pt``) gives the weights its run
      validated (:func:`training.checkpoint.tracker_from_checkpoint`).
    * Anything else goes through ``trackers.load``.
    * A learned tracker's bare name (``"p2b"``) would be a randomly initialised model: refused
      with :class:`UntrainedTrackerError` unless ``untrained=True``, and then initialised from
      ``seed`` (the global torch RNG is left as it was), so two runs score the same.

    Raises ``ValueError`` / ``FileNotFoundError`` naming ``name_or_path``.
    """
    if is_residual_file(name_or_path):  # a `pointtrack finetune --algo residual`
        from training.rl.wrappers import ResidualTracker  # the RL stack only when asked for

        return ResidualTracker.load(name_or_path)
    if is_training_checkpoint(name_or_path):
        return tracker_from_checkpoint(name_or_path)
    if find_checkpoint(name_or_path) is not None:
        return trackers.load(name_or_path)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        tracker = trackers.load(name_or_path)
    if isinstance(tracker, torch.nn.Module) and not untrained:
        raise UntrainedTrackerError(
            f"tracker {name_or_path!r} has no weights: it would be a randomly initialised model. "
            "Give a checkpoint (a shipped name such as p2b-kitti1-u, a tracker file, or a run's "
            "best.pt), or pass --untrained to use the random initialisation on purpose"
        )
    return tracker


def load_kernels(tracker: Any) -> None:
    """The env's compiled scan index and a learned tracker's compiled point ops loaded now
    (numba's start and its disk cache, ~0.8 s of CPU once per process), in a command's set-up:
    before an evaluation forks its workers (each eval seed, ``select`` candidate and world
    forks new ones, which inherit the kernels instead of each loading them again) and before a
    fine-tune's clock starts (its steps/s measures the loop, not the process's start-up).
    Nothing happens without numba (:func:`envs.kernels.load_kernels`,
    :func:`trackers.ops.load_kernels`, :func:`trackers.decision.load_kernels`)."""
    load_env_kernels()
    if isinstance(tracker, torch.nn.Module):
        ops.load_kernels()
        decision.load_kernels()
