"""Training checkpoints (``RUN/best.pt``, ``RUN/last.pt``) and the run directory around them.

A checkpoint is a ``torch.save`` dict (format :data:`CHECKPOINT_FORMAT`) holding the weights,
their moving average (when the run keeps one), optimizer, scheduler, decorrelation memory, RNG
states, epoch, step and the run's config. What this module guarantees:

* **Atomic writes**: :func:`atomic_save` writes through :func:`training.rundir.atomic_path`
  (a temporary sibling, fsynced and renamed into place), so a killed process leaves either the
  previous file or the new one, never a truncated one.
* **No code runs on load**: every read is ``torch.load(weights_only=True)``.
* **Validated reads**: :func:`read_checkpoint` refuses a file of another format naming the path;
  :func:`check_resumable` refuses a checkpoint of another tracker or config naming every differing
  key; :func:`load_weights` refuses non-finite weights naming the tensor.
The run directory around the checkpoints (fresh / resume, log truncation) is
:mod:`training.rundir`'s.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

import trackers
from trackers.provenance import UNKNOWN, Provenance
from trackers.registry import find_checkpoint, read_safetensors
from training.config import (
    IDENTITY_EXEMPT,
    LEGACY_DEFAULTS,
    TrainConfig,
    checkpoint_env_options,
    checkpoint_tracker_kwargs,
)
from training.provenance import train_provenance
from training.rundir import atomic_path, file_sha256

__all__ = [
    "checkpoint_provenance",
    "parent_entry",
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "atomic_save",
    "check_resumable",
    "config_differences",
    "is_training_checkpoint",
    "load_weights",
    "read_checkpoint",
    "restore_rng_state",
    "rng_state",
    "tracker_from_checkpoint",
]

CHECKPOINT_FORMAT = 1


class CheckpointError(ValueError):
    """A file that is not a usable training checkpoint (the message names the file)."""


def atomic_save(obj: Any, path: str | Path) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (:func:`training.rundir.atomic_path`)."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)


def rng_state() -> dict[str, Any]:
    """The global torch, numpy and python RNG states as tensors and plain values."""
    mt, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "numpy_keys": torch.from_numpy(keys.astype(np.int64)),
        "numpy_pos": int(pos),
        "numpy_has_gauss": int(has_gauss),
        "numpy_cached": float(cached),
        "python": [int(version), list(internal), gauss],
    }


def restore_rng_state(state: Mapping[str, Any]) -> None:
    """Set the global RNGs from :func:`rng_state`'s dict."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(
        (
            "MT19937",
            state["numpy_keys"].numpy().astype(np.uint32),
            state["numpy_pos"],
            state["numpy_has_gauss"],
            state["numpy_cached"],
        )
    )
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


def config_differences(
    checkpoint: Mapping[str, Any], current: Mapping[str, Any], label: str
) -> str:
    """``"key: checkpoint A vs <label> B, ..."`` for every key whose values differ; "" if none."""
    keys = sorted(k for k in set(checkpoint) | set(current) if checkpoint.get(k) != current.get(k))
    return ", ".join(
        f"{k}: checkpoint {checkpoint.get(k)!r} vs {label} {current.get(k)!r}" for k in keys
    )


def _identity(values: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in values.items() if k not in IDENTITY_EXEMPT}


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict at ``path`` (CPU tensors, read without running code).

    Raises :class:`CheckpointError` naming ``path`` when it cannot be read or is not a training
    checkpoint of this format."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many unrelated types for foreign files
        raise CheckpointError(f"{path} is not a training checkpoint: {exc}") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        found = ckpt.get("format") if isinstance(ckpt, dict) else None
        raise CheckpointError(
            f"{path} is not a training checkpoint (format {found!r}, expected {CHECKPOINT_FORMAT})"
        )
    return ckpt


def is_training_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a readable training checkpoint (``best.pt`` / ``last.pt``)."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        read_checkpoint(path)
    except CheckpointError:
        return False
    return True


def check_resumable(ckpt: Mapping[str, Any], cfg: TrainConfig, path: str | Path) -> None:
    """Refuse (``CheckpointError``) to resume ``cfg`` from a checkpoint of another tracker or of
    a config that differs in a key outside ``IDENTITY_EXEMPT`` (each such key is named)."""
    if ckpt.get("tracker") != cfg.tracker:
        raise CheckpointError(
            f"refusing to resume: {path} is a checkpoint of tracker {ckpt.get('tracker')!r}, "
            f"this run trains {cfg.tracker!r}"
        )
    # a key added to TrainConfig after the checkpoint was written ran at its default then, or
    # at its legacy value where the default changed since (recipe: v1)
    saved = {**_identity(TrainConfig().to_dict()), **LEGACY_DEFAULTS, **_identity(ckpt["config"])}
    details = config_differences(saved, _identity(cfg.to_dict()), "now")
    if details:
        raise CheckpointError(
            f"refusing to resume from {path}: it was trained with a different config ({details})"
        )


def load_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The validated weights and the config of a training checkpoint (``best.pt`` /
    ``last.pt``): the weight average when the run kept one, else the model's weights.

    Raises :class:`CheckpointError` naming ``path`` for a file that is not a training checkpoint
    and naming the tensor for non-finite weights."""
    return _validated_weights(read_checkpoint(path), path)


def _validated_weights(
    ckpt: Mapping[str, Any], path: str | Path
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    average = ckpt.get("ema") or {}
    weights = average.get("shadow") or ckpt["model"]
    for name, tensor in weights.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: tensor {name!r} holds NaN or inf values")
    return weights, ckpt["config"]


def tracker_from_checkpoint(path: str | Path) -> torch.nn.Module:
    """The tracker (CPU, eval mode) holding the validated weights of a training checkpoint
    (:func:`load_weights`), with the env options its run was validated with
    (``tracker.env_options``, :func:`training.config.checkpoint_env_options`) and the
    provenance it records (``tracker.provenance``, :mod:`training.provenance`), ready for
    ``trackers.save`` or evaluation."""
    ckpt = read_checkpoint(path)
    weights, config = _validated_weights(ckpt, path)
    model = trackers.make(config["tracker"], **checkpoint_tracker_kwargs(config))
    model.load_state_dict(weights)
    model.env_options = checkpoint_env_options(config)
    model.provenance = checkpoint_provenance(ckpt)
    return model.eval()


def parent_entry(spec: str) -> dict[str, Any]:
    """``{"name", "sha256", "provenance"}`` of the checkpoint a run starts from (a tracker file,
    a shipped name or a training checkpoint); its provenance unknown when it records none."""
    path = find_checkpoint(spec)
    if path is None:
        return {"name": str(spec), "sha256": UNKNOWN, "provenance": Provenance()}
    if is_training_checkpoint(path):
        provenance = checkpoint_provenance(read_checkpoint(path))
    elif path.suffix == ".safetensors":
        meta, _ = read_safetensors(path, "tracker checkpoint")
        provenance = Provenance.from_json(meta.get("provenance"), f"{path}: provenance")
    else:  # a .pt tracker file: trackers.load reads it (and its provenance) safely
        provenance = trackers.load(path).provenance
    return {"name": str(spec), "sha256": file_sha256(path), "provenance": provenance}


def checkpoint_provenance(ckpt: Mapping[str, Any]) -> Provenance:
    """The provenance a training checkpoint (``best.pt`` / ``last.pt``) records; one written
    before provenance existed gets what its config says, the commit and world digest unknown."""
    raw = ckpt.get("provenance")
    if raw is not None:
        return Provenance.from_json(raw, "training checkpoint provenance")
    config = ckpt["config"]
    init = config.get("init_weights")
    return train_provenance(
        config,
        None,
        int(ckpt.get("step", 0)),
        parent=parent_entry(init) if init else None,
        commit=UNKNOWN,
    )
