"""The resume state of a fine-tuning run: ``state.safetensors`` (policy and optimizer tensors,
the torch RNG state and JSON metadata), written atomically and read without unpickling (SB3's
``PPO.load`` runs cloudpickle: a crafted zip can execute code)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open

from training.rl.config import FinetuneError
from training.rundir import atomic_save_safetensors

__all__ = ["STATE_FORMAT", "load_state", "read_state_meta", "save_state"]

STATE_FORMAT = "pointtrack-finetune-state"
STATE_VERSION = "1"


def read_state_meta(path: str | Path) -> dict[str, Any]:
    """The JSON metadata of a ``state.safetensors``; :class:`FinetuneError` naming ``path`` for
    a file that is not one."""
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = dict(f.metadata() or {})
    except Exception as exc:
        raise FinetuneError(
            f"cannot read {path}: not a safetensors file ({type(exc).__name__}: {exc})"
        ) from exc
    if meta.get("format") != STATE_FORMAT:
        raise FinetuneError(
            f"{path} is not a pointtrack finetune state (format={meta.get('format')!r})"
        )
    return json.loads(meta["state"])


def save_state(
    path: Path, policy: torch.nn.Module, optimizer: torch.optim.Optimizer, meta: dict[str, Any]
) -> None:
    """Policy and optimizer tensors plus JSON ``meta`` into one safetensors file (atomic)."""
    tensors = {f"policy.{k}": v.detach().cpu().contiguous() for k, v in policy.state_dict().items()}
    opt = optimizer.state_dict()
    for idx, entry in opt["state"].items():
        for key, value in entry.items():
            tensors[f"optim.{idx}.{key}"] = torch.as_tensor(value).detach().cpu().contiguous()
    tensors["rng.torch"] = torch.get_rng_state()
    groups = [dict(g) for g in opt["param_groups"]]
    meta = {**meta, "optimizer_groups": groups}
    atomic_save_safetensors(
        path,
        tensors,
        {"format": STATE_FORMAT, "version": STATE_VERSION, "state": json.dumps(meta)},
    )


def load_state(
    path: str | Path,
) -> tuple[dict[str, torch.Tensor], dict[str, Any], torch.Tensor, dict[str, Any]]:
    """-> (policy state dict, optimizer state dict, torch RNG state, metadata); safetensors
    only (no unpickling)."""
    meta = read_state_meta(path)
    policy, state = {}, {}
    with safe_open(str(path), framework="pt", device="cpu") as f:
        for key in f.keys():  # noqa: SIM118 - safe_open API
            tensor = f.get_tensor(key)
            if key.startswith("policy."):
                policy[key[len("policy.") :]] = tensor
            elif key.startswith("optim."):
                _, idx, name = key.split(".", 2)
                state.setdefault(int(idx), {})[name] = tensor
        rng = f.get_tensor("rng.torch")
    optim = {"state": state, "param_groups": meta["optimizer_groups"]}
    return policy, optim, rng, meta
