"""The pretraining configuration: one dataclass, filled from defaults, a YAML file and CLI flags.

Precedence: defaults < YAML file (``--config FILE``) < explicit CLI flags (and ``--set key=value``).
Every source is validated before training starts: unknown keys and invalid values raise
:class:`ConfigError` naming each offending key.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "IDENTITY_EXEMPT",
    "ConfigError",
    "TrainConfig",
    "config_from_dict",
    "load_config",
    "parse_value",
    "tracker_config",
]

TRACKERS = ("p2b", "bat", "gpt")
MODEL_SIZES = ("default", "slim")

_SLIM_BACKBONE = {"channels": [[32, 32, 64], [64, 64, 128], [128, 128, 128]],
                  "out_channels": 128, "neighbours": 16, "ragged_train": True}
# Reduced widths for CPU training (the shipped checkpoints): about 6x cheaper per step than the
# papers' widths, same architecture, same inputs (512 / 1024 points). Ragged training (BatchNorm
# statistics over real ball-query hits only) saves another ~30 % of a CPU step.
SLIM = {
    "p2b": {"backbone": _SLIM_BACKBONE, "hidden_channels": 64, "out_channels": 128,
            "head": {"vote_channels": 128}},
    "bat": {"backbone": _SLIM_BACKBONE, "hidden_channels": 64, "out_channels": 128,
            "head": {"vote_channels": 128}},
    "gpt": {"backbone": _SLIM_BACKBONE, "node_channels": 64, "itc_channels": 64,
            "out_channels": 128, "head": {"vote_channels": 128}},
}


def tracker_config(tracker: str, model_size: str = "default", extra: dict | None = None) -> dict:
    """The kwargs of ``trackers.make(tracker, ...)`` for a model size, updated by ``extra``."""
    import copy

    base = copy.deepcopy(SLIM[tracker]) if model_size == "slim" else {}
    base.update(extra or {})
    return base


WEIGHTINGS = ("none", "decorrelation", "sam")
DRCT_VARIANTS = ("asymmetric", "siamese")  # training.drct.DRCT_VARIANTS (no torch import here)
DATASETS = ("synthetic", "kitti")


class ConfigError(ValueError):
    """An invalid training configuration (the message names every offending key)."""


@dataclass
class TrainConfig:
    """Everything a pretraining run depends on. Defaults follow GPT's "Implementation Details"
    (Adam, lr 1e-3 decayed x0.2 every 12 epochs, batch 48) and ``000_…`` Sec. III-C / IV-B."""

    # what is trained
    tracker: str = "p2b"
    model_size: str = "default"  # default (papers' widths) | slim (see SLIM)
    tracker_config: dict = field(default_factory=dict)  # extra kwargs of trackers.make
    # start from these weights (a tracker checkpoint file or a shipped checkpoint name, same
    # tracker and config); a fresh optimizer and schedule, unlike --resume
    init_weights: str | None = None
    weighting: str = "none"  # none (-U) | decorrelation (-W) | sam (-S)
    # data
    dataset: str = "synthetic"
    preset: str = "default"  # synthetic world preset
    sensor: str = "hdl64"
    world_seed: int = 0
    data_root: str | None = None  # KITTI root (dataset=kitti) or an existing synthetic root
    setting: str | None = "kitti-1"  # class-agnostic setting (observed categories are trained)
    category: str | None = None  # class-specific mode: train on this one category instead
    candidates_per_frame: int = 4
    # object resizing, scale per box axis ~ U(1 - a, 1 + a); 0 = off (the papers' samples); see
    # training.samples
    size_jitter: float = 0.0
    # optimisation
    epochs: int = 36
    batch_size: int = 48
    lr: float = 1e-3
    lr_step_epochs: int = 12
    lr_gamma: float = 0.2
    weight_decay: float = 0.0
    grad_clip: float | None = None
    # exponential moving average of the weights (0 = off); validated and exported when on, see
    # training.averaging
    ema_decay: float = 0.0
    iters_per_epoch: int | None = None  # cap: a fresh random subset of samples every epoch
    seed: int = 0
    # SAM (-S)
    sam_rho: float = 0.05
    # feature decorrelation (-W)
    rff_functions: int = 5
    decor_iters: int = 20
    decor_lr: float = 1.0
    decor_decay_every: int = 10
    decor_momentum: float = 0.9
    decor_penalty: float = 0.1
    decor_memory: bool = True
    decor_memory_ratio: float = 0.9
    # DRCT (training.drct; docs/weather.md): dual-branch training with domain randomisation and
    # local geometric contrast; domain_randomize is the -RD control (plain training on
    # randomised samples). Defaults: the paper's where it gives them, else ours (documented).
    drct: bool = False
    drct_variant: str = "asymmetric"  # asymmetric (extra FFN on the auxiliary branch) | siamese
    drct_contrast_weight: float = 0.01
    drct_aux_weight: float = 1.0
    drct_radius_m: float = 0.7
    drct_neighbours: int = 8
    drct_detach_aux: bool = True
    drct_ffn_ratio: float = 2.0
    domain_randomize: bool = False
    dr_p_skip: float = 0.5
    dr_p_step: float = 0.5
    dr_max_noise_ratio: float = 0.1
    dr_max_drop_ratio: float = 0.3
    dr_jitter_m: float = 0.02
    # validation (OPE on the val split)
    val_every: int = 1
    val_max_tracklets: int | None = None
    val_max_frames: int | None = None  # truncate each val tracklet to this many frames
    # runtime
    num_workers: int = 0
    num_threads: int | None = None
    device: str = "cpu"
    progress: bool = True
    out: str = "runs/train"

    def validate(self) -> TrainConfig:
        errors: list[str] = []

        def bad(key: str, why: str) -> None:
            errors.append(f"{key}={getattr(self, key)!r}: {why}")

        if self.tracker not in TRACKERS:
            bad("tracker", f"must be one of {', '.join(TRACKERS)}")
        if self.model_size not in MODEL_SIZES:
            bad("model_size", f"must be one of {', '.join(MODEL_SIZES)}")
        if self.weighting not in WEIGHTINGS:
            bad("weighting", f"must be one of {', '.join(WEIGHTINGS)}")
        if self.dataset not in DATASETS:
            bad("dataset", f"must be one of {', '.join(DATASETS)}")
        if self.dataset == "kitti" and not self.data_root:
            bad("data_root", "dataset=kitti needs data_root (the KITTI tracking root)")
        if self.setting is None and self.category is None:
            bad("setting", "give a setting (class-agnostic) or a category (class-specific)")
        for key in ("epochs", "batch_size", "candidates_per_frame", "lr_step_epochs",
                    "rff_functions", "val_every"):
            if getattr(self, key) < 1:
                bad(key, "must be >= 1")
        for key in ("iters_per_epoch", "val_max_tracklets", "val_max_frames", "num_threads"):
            value = getattr(self, key)
            if value is not None and value < 1:
                bad(key, "must be >= 1 or null")
        for key in ("lr", "decor_lr"):
            if not getattr(self, key) > 0:
                bad(key, "must be > 0")
        if not 0 < self.lr_gamma <= 1:
            bad("lr_gamma", "must be in (0, 1]")
        for key in ("weight_decay", "sam_rho", "decor_penalty", "decor_iters", "num_workers",
                    "decor_decay_every"):
            if getattr(self, key) < 0:
                bad(key, "must be >= 0")
        if not 0 <= self.size_jitter < 1:
            bad("size_jitter", "must be in [0, 1)")
        if not 0 <= self.ema_decay < 1:
            bad("ema_decay", "must be in [0, 1) (0 = off)")
        if not 0 <= self.decor_momentum < 1:
            bad("decor_momentum", "must be in [0, 1)")
        if not 0 <= self.decor_memory_ratio < 1:
            bad("decor_memory_ratio", "must be in [0, 1)")
        if self.init_weights is not None and not self.init_weights.strip():
            bad("init_weights", "must be a checkpoint file or a shipped checkpoint name, or null")
        if self.grad_clip is not None and not self.grad_clip > 0:
            bad("grad_clip", "must be > 0 or null")
        if self.weighting == "decorrelation" and self.batch_size < 2:
            bad("batch_size", "decorrelation weighting needs batch_size >= 2")
        if self.drct_variant not in DRCT_VARIANTS:
            bad("drct_variant", f"must be one of {', '.join(DRCT_VARIANTS)}")
        if self.drct and self.tracker not in TRACKERS:
            bad("drct", f"needs a learned tracker ({', '.join(TRACKERS)}), not a baseline")
        if self.drct and self.domain_randomize:
            bad("domain_randomize", "is the -RD control of DRCT; use drct or domain_randomize")
        for key in ("drct_contrast_weight", "drct_aux_weight", "dr_jitter_m"):
            if not getattr(self, key) >= 0:
                bad(key, "must be >= 0")
        for key in ("drct_radius_m", "drct_ffn_ratio"):
            if not getattr(self, key) > 0:
                bad(key, "must be > 0")
        if self.drct_neighbours < 1:
            bad("drct_neighbours", "must be >= 1")
        for key in ("dr_p_skip", "dr_p_step", "dr_max_noise_ratio", "dr_max_drop_ratio"):
            if not 0 <= getattr(self, key) <= 1:
                bad(key, "must be in [0, 1]")
        if self.device != "cpu" and not self.device.startswith("cuda"):
            bad("device", "must be cpu or cuda[:N]")
        if errors:
            raise ConfigError("invalid training config: " + "; ".join(errors))
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def make_kwargs(self) -> dict:
        """Keyword arguments of ``trackers.make(self.tracker, ...)``."""
        return tracker_config(self.tracker, self.model_size, self.tracker_config)


# Keys that may change between a run and its resumption (they do not change the result).
IDENTITY_EXEMPT = frozenset(
    {"epochs", "out", "num_workers", "num_threads", "progress", "device", "val_every",
     "val_max_tracklets", "val_max_frames"}
)

_FIELDS = {f.name: f for f in dataclasses.fields(TrainConfig)}
_HINTS = typing.get_type_hints(TrainConfig)


def _check_type(key: str, value: Any) -> Any:
    """Coerce ``value`` to the field's type or raise a one-line reason."""
    hint = _HINTS[key]
    args = typing.get_args(hint)
    optional = isinstance(hint, types.UnionType) and type(None) in args
    base = next((a for a in args if a is not type(None)), hint) if optional else hint
    if value is None:
        if optional:
            return None
        raise TypeError("may not be null")
    if base is bool:
        if isinstance(value, bool):
            return value
        raise TypeError("must be true or false")
    if base is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError("must be an integer")
        return value
    if base is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError("must be a number")
        return float(value)
    if base is str:
        if not isinstance(value, str):
            raise TypeError("must be a string")
        return value
    if base is dict:
        if not isinstance(value, dict):
            raise TypeError("must be a mapping")
        return dict(value)
    return value


def config_from_dict(values: dict[str, Any], base: TrainConfig | None = None) -> TrainConfig:
    """A validated config: ``base`` (or the defaults) updated by ``values``."""
    if not isinstance(values, dict):
        raise ConfigError(f"a training config must be a mapping, got {type(values).__name__}")
    unknown = sorted(k for k in values if k not in _FIELDS)
    errors = []
    if unknown:
        errors.append(f"unknown keys: {', '.join(unknown)} (valid: {', '.join(sorted(_FIELDS))})")
    cfg = dataclasses.replace(base) if base is not None else TrainConfig()
    for key, value in values.items():
        if key in unknown:
            continue
        try:
            setattr(cfg, key, _check_type(key, value))
        except TypeError as exc:
            errors.append(f"{key}={value!r}: {exc}")
    try:
        cfg.validate()
    except ConfigError as exc:
        errors.extend(str(exc).removeprefix("invalid training config: ").split("; "))
    if errors:
        raise ConfigError("invalid training config: " + "; ".join(errors))
    return cfg


def load_config(path: str | Path, base: TrainConfig | None = None) -> TrainConfig:
    """Read a YAML file of config keys (a flat mapping) on top of ``base``."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from exc
    try:
        values = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from exc
    try:
        return config_from_dict(values, base)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def parse_value(text: str) -> Any:
    """A ``--set key=value`` value, read as YAML (``3`` -> int, ``null`` -> None, ``a`` -> str)."""
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text
