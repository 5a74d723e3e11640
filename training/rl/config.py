"""The fine-tuning config (:class:`FinetuneConfig`) and its validation.

Errors name config fields (``group_size must be ...``) and carry them in
:attr:`FinetuneError.fields`; ``pointtrack finetune`` turns each into its flag
(``--group-size``). Everything here is checked before a run builds data or writes a file.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from envs.tracking_env import REWARDS
from training.argconfig import read_yaml_mapping
from training.config import coerce
from training.rl.policy import ACTION_MODES, CRITICS, TRAIN_PARTS

__all__ = [
    "ALGOS",
    "BASELINES",
    "MAX_GROUP_SIZE",
    "RESUMABLE",
    "FinetuneConfig",
    "FinetuneError",
    "NonFiniteError",
    "config_from_values",
    "read_hyperparams",
]

ALGOS = ("ppo", "group", "residual")
BASELINES = ("critic", "self_critical")
#: Config fields that may change on ``--resume`` (how long and where it runs, not what).
RESUMABLE = (
    "timesteps",
    "device",
    "threads",
    "save_every",
    "snapshot_every",
    "val_max_tracklets",
    "logger",
)
#: SB3 logger outputs (``stable_baselines3.common.logger.configure``) a run may write
LOGGER_FORMATS = ("tensorboard", "csv", "json", "stdout")
#: RL Zoo hyper-parameter names read as the config's fields (``--config FILE.yml``)
ZOO_NAMES = {"n_timesteps": "timesteps", "n_envs": "num_envs", "learning_rate": "lr"}
#: the largest ``group_size``: each state's samples are scored one env call each, so a larger
#: group only costs time (and a huge one the memory of its ``(S, K, 4)`` rollout arrays)
MAX_GROUP_SIZE = 1024


class FinetuneError(ValueError):
    """An expected failure (bad config, refused run directory): the CLI prints one line.

    ``fields``: the config fields the message names (by field name; the CLI turns each into
    its flag)."""

    def __init__(self, message: str, fields: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.fields = tuple(fields)


class NonFiniteError(FinetuneError):
    """A NaN or inf in a rollout, a loss or the weights; the last good checkpoint is kept."""


@dataclass
class FinetuneConfig:
    """Everything a fine-tuning run depends on (``pointtrack finetune`` flags)."""

    tracker: str = "p2b-kitti1-u"
    algo: str = "ppo"
    # data: the synthetic world (preset, sensor, world_seed) or a KITTI-layout root
    setting: str = "kitti-1"
    preset: str = "default"
    sensor: str = "hdl64"
    world_seed: int = 0
    data_root: str | None = None
    reward: str = "iou_3d"
    clip_length: int = 32  # steps per episode (0: whole tracklets)
    # PPO
    timesteps: int = 4096
    num_envs: int = 4
    n_steps: int = 64  # per sub-env and update
    batch_size: int = 64
    n_epochs: int = 4
    lr: float = 3e-4  # value head and log-std
    tracker_lr: float = 1e-5
    train_parts: str = "head"
    action_mode: str = "best"
    critic: str = "fused"
    baseline: str = "critic"  # or "self_critical" (needs gamma=0): wrappers.SelfCriticalReward
    log_std_init: float = -2.0
    warmup_rollouts: int = 1
    target_kl: float | None = 0.02
    clip_range: float = 0.1
    max_grad_norm: float = 0.5
    gamma: float = 0.9
    group_size: int = 8  # --algo group: sampled actions per state
    gae_lambda: float = 0.95
    ent_coef: float = 0.0
    seed: int = 0
    device: str = "cpu"
    threads: int | None = None  # torch threads (None: every usable core)
    save_every: int = 1  # updates between resume checkpoints
    snapshot_every: int = 0  # updates between tracker snapshots (0: none)
    val_max_tracklets: int = 8
    #: SB3 logger outputs under OUT/sb3, comma-separated (LOGGER_FORMATS; "": log.jsonl only)
    logger: str = ""
    #: accept a learned tracker's bare name (a random initialisation from ``seed``)
    untrained: bool = False
    #: train in an env serving a category the base file holds out (training.provenance)
    allow_held_out: bool = False

    def problems(self) -> list[tuple[str, str]]:
        """``(field, message)`` for every offending field (empty when the config is valid)."""
        errors: list[tuple[str, str]] = []
        for name, valid in (
            ("algo", ALGOS),
            ("train_parts", TRAIN_PARTS),
            ("action_mode", ACTION_MODES),
            ("critic", CRITICS),
            ("baseline", BASELINES),
            ("reward", REWARDS),
        ):
            value = getattr(self, name)
            if value not in valid:
                errors.append((name, f"{name} must be one of {list(valid)}, got {value!r}"))
        if not 2 <= self.group_size <= MAX_GROUP_SIZE:
            low = "must be >= 2" if self.group_size < 2 else f"must be <= {MAX_GROUP_SIZE}"
            errors.append(("group_size", f"group_size {low}, got {self.group_size}"))
        if self.algo == "group" and self.baseline != "critic":
            errors.append(
                (
                    "baseline",
                    f"baseline {self.baseline!r} does not apply to algo 'group' (its baseline "
                    f"is the group's mean reward)",
                )
            )
        for name in ("timesteps", "num_envs", "n_epochs", "threads", "save_every"):
            value = getattr(self, name)
            if value is not None and value < 1:  # threads None: every usable core
                errors.append((name, f"{name} must be >= 1, got {value}"))
        for name in ("n_steps", "batch_size"):
            if getattr(self, name) < 2:
                errors.append((name, f"{name} must be >= 2, got {getattr(self, name)}"))
        for name in ("clip_length", "warmup_rollouts", "snapshot_every", "world_seed", "seed"):
            if getattr(self, name) < 0:
                errors.append((name, f"{name} must be >= 0, got {getattr(self, name)}"))
        if self.val_max_tracklets < 0:
            errors.append(
                (
                    "val_max_tracklets",
                    f"val_max_tracklets must be >= 1 (or 0 for no val check), got "
                    f"{self.val_max_tracklets}",
                )
            )
        for name in ("lr", "tracker_lr", "clip_range", "max_grad_norm", "ent_coef"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                errors.append((name, f"{name} must be a finite number >= 0, got {v}"))
        if not math.isfinite(self.log_std_init):
            errors.append(("log_std_init", f"log_std_init must be finite, got {self.log_std_init}"))
        for name in ("gamma", "gae_lambda"):
            if not 0 <= getattr(self, name) <= 1:
                errors.append((name, f"{name} must be in [0, 1], got {getattr(self, name)}"))
        if self.baseline == "self_critical" and self.gamma != 0:
            errors.append(
                (
                    "gamma",
                    f"baseline 'self_critical' is unbiased for one-step returns only: set "
                    f"gamma=0 (got gamma={self.gamma})",
                )
            )
        if str(self.device).startswith("cuda") and not torch.cuda.is_available():
            errors.append(("device", f"device {self.device!r}: CUDA is not available here"))
        elif not str(self.device).startswith(("cpu", "cuda")):
            errors.append(("device", f"device must be cpu or cuda[:N], got {self.device!r}"))
        for kind in self.logger_formats:
            if kind not in LOGGER_FORMATS:
                errors.append(
                    ("logger", f"logger must list some of {list(LOGGER_FORMATS)}, got {kind!r}")
                )
            elif kind == "tensorboard" and importlib.util.find_spec("tensorboard") is None:
                errors.append(
                    (
                        "logger",
                        "logger 'tensorboard' needs the tensorboard package: "
                        "pip install 'pointtrack[tensorboard]'",
                    )
                )
        if self.target_kl is not None and not self.target_kl > 0:
            errors.append(("target_kl", f"target_kl must be > 0 (or None), got {self.target_kl}"))
        return errors

    def validate(self) -> None:
        """Raise :class:`FinetuneError` naming every offending field (nothing is built or
        written before this passes)."""
        errors = self.problems()
        if errors:
            raise FinetuneError("; ".join(m for _, m in errors), [f for f, _ in errors])

    @property
    def logger_formats(self) -> list[str]:
        """:attr:`logger` as a list (empty entries dropped)."""
        return [kind.strip() for kind in self.logger.split(",") if kind.strip()]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


_HINTS = typing.get_type_hints(FinetuneConfig)


def config_from_values(
    values: Mapping[str, Any], base: FinetuneConfig | None = None, *, where: str = ""
) -> FinetuneConfig:
    """``base`` (default: the defaults) with ``values`` (field name -> value) applied, each
    coerced to its field's type; :class:`FinetuneError` naming every unknown key or bad value
    (prefixed by ``where``, e.g. the file). The result is not yet :meth:`validated
    <FinetuneConfig.validate>`."""
    errors: list[tuple[str, str]] = []
    known = {f.name for f in dataclasses.fields(FinetuneConfig)}
    cfg = dataclasses.replace(base) if base is not None else FinetuneConfig()
    for key, value in values.items():
        if key not in known:
            errors.append((key, f"unknown key {key!r} (valid: {', '.join(sorted(known))})"))
            continue
        try:
            setattr(cfg, key, coerce(_HINTS[key], value))
        except TypeError as exc:
            errors.append((key, f"{key}={value!r}: {exc}"))
    if errors:
        prefix = f"{where}: " if where else ""
        raise FinetuneError(prefix + "; ".join(m for _, m in errors), [k for k, _ in errors])
    return cfg


def read_hyperparams(path: str | Path) -> dict[str, Any]:
    """An RL Zoo-style hyper-parameter file: a YAML mapping of :class:`FinetuneConfig` fields
    (the RL Zoo's ``n_timesteps``, ``n_envs`` and ``learning_rate`` read as ``timesteps``,
    ``num_envs`` and ``lr``). :class:`FinetuneError` naming the file when it cannot be read,
    is not a mapping, or names a field twice."""
    try:
        values = read_yaml_mapping(path)
    except ValueError as exc:
        raise FinetuneError(f"config file {exc}") from None
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = ZOO_NAMES.get(str(key), str(key))
        if name in out:
            raise FinetuneError(f"config file {path}: {name!r} is given twice ({key!r})", [name])
        out[name] = value
    return out
