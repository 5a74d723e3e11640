"""The pretraining configuration: one dataclass, filled from defaults, a YAML file and CLI flags.

Precedence: defaults < YAML file (``--config FILE``) < explicit CLI flags (and ``--set key=value``).
Every source is validated before training starts: unknown keys and invalid values raise
:class:`ConfigError` naming each offending key.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import trackers
from envs.data.nuscenes import NUSCENES_FRAMES
from envs.data.settings import check_setting_layout
from envs.observation import SEARCH_OFFSET_M, SEARCH_SCALE
from trackers.registry import default_env_options
from training.argconfig import read_yaml_mapping
from training.scalars import parse_formats

__all__ = [
    "IDENTITY_EXEMPT",
    "LEGACY_DEFAULTS",
    "RECIPES",
    "ConfigError",
    "TrainConfig",
    "checkpoint_env_options",
    "checkpoint_tracker_kwargs",
    "coerce",
    "config_from_dict",
    "load_config",
    "parse_value",
    "tracker_config",
]


def tracker_config(tracker: str, model_size: str = "default", extra: dict | None = None) -> dict:
    """The kwargs of ``trackers.make(tracker, ...)`` for a model size (the tracker class's
    ``sizes``, :func:`trackers.size_config`), updated by ``extra``: nested dicts merge, so
    ``{"head": {"positive_fraction": 0.2}}`` keeps the size's other head fields."""
    return _merged(trackers.size_config(tracker, model_size), extra or {})


def _merged(base: dict, extra: dict) -> dict:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            value = _merged(out[key], value)
        out[key] = value
    return out


WEIGHTINGS = ("none", "decorrelation", "sam")
DATASETS = ("synthetic", "kitti", "nuscenes")
LOSS_REDUCTIONS = ("sample", "pooled")
INITS = ("default", "kaiming")

# The training recipes (docs/recipe.md): v1 is the recipe of every checkpoint shipped before
# issue 24; v2 follows Open3DSOT's code (the reference framework of P2B and BAT) item by item.
# Each key is also a TrainConfig field; None there means "the recipe's value".
RECIPES: dict[str, dict[str, Any]] = {
    "v1": {
        "zero_offset_candidate": False,
        "min_crop_points": 0,
        "template_union": False,
        "frame0_samples": False,
        "limit_box": False,
        "loss_reduction": "sample",
        "adam_beta1": 0.9,
        "adam_eps": 1e-8,
        "bat_fps": False,
        "init": "default",
        "gpt_search_region": False,
    },
    "v2": {
        "zero_offset_candidate": True,
        "min_crop_points": 21,
        "template_union": True,
        "frame0_samples": True,
        "limit_box": True,
        "loss_reduction": "pooled",
        "adam_beta1": 0.5,
        "adam_eps": 1e-6,
        "bat_fps": True,
        "init": "kaiming",
        "gpt_search_region": True,
    },
}
GPT_SEARCH_ENLARGEMENT = (1.0, 4.0)
"""``(scale, offset_m)`` of GPT's search region (its paper: the previous box plus 4 m on every
edge, no scaling), used for GPT when ``gpt_search_region`` is on."""

# Values of keys a training checkpoint written before the key existed ran with (not the
# current default): runs before recipe v2 are v1 runs.
LEGACY_DEFAULTS: dict[str, Any] = {"recipe": "v1"}
SEARCH_CENTERS = ("current", "previous")  # training.samples.SEARCH_CENTERS (no torch here)
DRCT_VARIANTS = ("asymmetric", "siamese")  # training.drct.DRCT_VARIANTS (no torch import here)


class ConfigError(ValueError):
    """An invalid training configuration (the message names every offending key)."""


@dataclass
class TrainConfig:
    """Everything a pretraining run depends on. Defaults follow GPT's "Implementation Details"
    (Adam, lr 1e-3 decayed x0.2 every 12 epochs, batch 48) and Tian et al. (TIP 2024) Sec. III-C /
    IV-B."""

    # what is trained
    tracker: str = "p2b"
    model_size: str = "default"  # default (papers' widths) | slim: the tracker class's `sizes`
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
    # dataset=nuscenes: table folder (default v1.0-trainval under data_root, else v1.0-mini: the
    # synthetic world written in nuScenes layout)
    nuscenes_version: str | None = None
    # dataset=nuscenes: the LiDAR frame served, lidar (each key frame's own) | scene (the scene's
    # first key frame's: ego motion removed, as Open3DSOT's global frame; envs.data.nuscenes)
    nuscenes_frame: str = "lidar"
    setting: str | None = "kitti-1"  # class-agnostic setting (observed categories are trained)
    category: str | None = None  # class-specific mode: train on this one category instead
    candidates_per_frame: int = 4
    # object resizing, scale per box axis ~ U(1 - a, 1 + a); 0 = off (the papers' samples); see
    # training.samples
    size_jitter: float = 0.0
    # the training recipe (v1 | v2, see RECIPES and docs/recipe.md) and its items, each
    # overridable on its own (null = the recipe's value). v1 stays the default until the
    # ablation of docs/recipe.md has run: v2's pilot runs did not yet train
    # (docs/notes/recipe-experiments.md)
    recipe: str = "v1"
    zero_offset_candidate: bool | None = None  # candidate 0 of every frame: unperturbed search
    min_crop_points: int | None = None  # redraw samples whose template or search crop has fewer
    template_union: bool | None = None  # 512 template points from the first + previous union
    frame0_samples: bool | None = None  # also sample t = 0 (previous = current = frame 0)
    limit_box: bool | None = None  # Open3DSOT's limit_box: large search offsets redrawn U(-1, 1)
    loss_reduction: str | None = None  # sample (per-sample means) | pooled (over the batch)
    adam_beta1: float | None = None
    adam_eps: float | None = None
    bat_fps: bool | None = None  # BAT's backbone samples by farthest-point sampling
    init: str | None = None  # default (torch's) | kaiming (kaiming-normal weights)
    gpt_search_region: bool | None = None  # GPT crops its search region by +4 m, no x1.25
    # the search region, in training, the val env and the tracker file's env options: the
    # previous box scaled by search_scale plus search_offset_m a side (null: the tracker's and
    # recipe's, 1.25 and 2 m); training cuts it around the Gaussian-perturbed current box
    # (search_center=current, P2B's) or previous box (previous: the target's own move between
    # the frames stays in the sample, as in tracking; for frames far apart, nuScenes' 2 Hz)
    search_scale: float | None = None
    search_offset_m: float | None = None
    search_center: str = "current"
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
    # scalar outputs in OUT/logs (training.scalars): a comma list of csv, json, tensorboard
    logger: str = "csv,json"
    out: str = "runs/train"

    def validate(self) -> TrainConfig:
        errors: list[str] = []

        def bad(key: str, why: str) -> None:
            errors.append(f"{key}={getattr(self, key)!r}: {why}")

        learned = trackers.available("learned")
        if self.tracker not in learned:
            bad("tracker", f"must be one of {', '.join(learned)}")
        elif self.model_size not in trackers.tracker_class(self.tracker).sizes:
            sizes = trackers.tracker_class(self.tracker).sizes
            bad("model_size", f"must be one of {', '.join(sizes)} for {self.tracker}")
        if self.weighting not in WEIGHTINGS:
            bad("weighting", f"must be one of {', '.join(WEIGHTINGS)}")
        if self.dataset not in DATASETS:
            bad("dataset", f"must be one of {', '.join(DATASETS)}")
        if self.dataset == "kitti" and not self.data_root:
            bad("data_root", "dataset=kitti needs data_root (the KITTI tracking root)")
        if self.nuscenes_frame not in NUSCENES_FRAMES:
            bad("nuscenes_frame", f"must be one of {', '.join(NUSCENES_FRAMES)}")
        elif self.nuscenes_frame != "lidar" and self.dataset != "nuscenes":
            bad("nuscenes_frame", f"applies to dataset=nuscenes, not {self.dataset!r}")
        if self.setting is None and self.category is None:
            bad("setting", "give a setting (class-agnostic) or a category (class-specific)")
        elif self.setting is not None and self.dataset in DATASETS:
            try:
                layout = "nuscenes" if self.dataset == "nuscenes" else "kitti"
                check_setting_layout(self.setting, layout)
            except ValueError as exc:
                bad("setting", str(exc))
        for key in (
            "epochs",
            "batch_size",
            "candidates_per_frame",
            "lr_step_epochs",
            "rff_functions",
            "val_every",
        ):
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
        for key in (
            "weight_decay",
            "sam_rho",
            "decor_penalty",
            "decor_iters",
            "num_workers",
            "decor_decay_every",
        ):
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
        try:
            parse_formats(self.logger)
        except ValueError:
            bad("logger", "must be a comma list of csv, json, tensorboard (each at most once)")
        if self.weighting == "decorrelation" and self.batch_size < 2:
            bad("batch_size", "decorrelation weighting needs batch_size >= 2")
        if self.recipe not in RECIPES:
            bad("recipe", f"must be one of {', '.join(RECIPES)}")
        if self.loss_reduction is not None and self.loss_reduction not in LOSS_REDUCTIONS:
            bad("loss_reduction", f"must be one of {', '.join(LOSS_REDUCTIONS)} or null")
        if self.init is not None and self.init not in INITS:
            bad("init", f"must be one of {', '.join(INITS)} or null")
        if self.min_crop_points is not None and self.min_crop_points < 0:
            bad("min_crop_points", "must be >= 0 or null")
        if self.adam_beta1 is not None and not 0 <= self.adam_beta1 < 1:
            bad("adam_beta1", "must be in [0, 1) or null")
        if self.adam_eps is not None and not self.adam_eps > 0:
            bad("adam_eps", "must be > 0 or null")
        self._validate_search(bad)
        if self.drct_variant not in DRCT_VARIANTS:
            bad("drct_variant", f"must be one of {', '.join(DRCT_VARIANTS)}")
        if self.tracker in learned and not _drct_trainable(trackers.tracker_class(self.tracker)):
            for key in ("drct", "domain_randomize"):
                if getattr(self, key):
                    bad(
                        key,
                        "needs a matching tracker (backbone -> fusion -> head) or mbptrack, "
                        f"not {self.tracker!r}",
                    )
        if (
            (self.drct or self.domain_randomize)
            and self.recipe in RECIPES
            and self.recipe_value("loss_reduction") == "pooled"
        ):
            bad("loss_reduction", "DRCT and -RD add per-sample terms to the total: use 'sample'")
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

    def _validate_search(self, bad: Callable[[str, str], None]) -> None:
        """The search-region keys, and what the tracker's samples support."""
        if self.search_scale is not None and not self.search_scale > 0:
            bad("search_scale", "must be > 0 or null")
        if self.search_offset_m is not None and not self.search_offset_m >= 0:
            bad("search_offset_m", "must be >= 0 or null")
        if self.search_center not in SEARCH_CENTERS:
            bad("search_center", f"must be one of {', '.join(SEARCH_CENTERS)}")
        if self.tracker not in trackers.available("learned"):
            return
        recipe = getattr(trackers.tracker_class(self.tracker), "sample_recipe", None)
        for key in ("search_scale", "search_offset_m"):
            if recipe == "motion" and getattr(self, key) is not None:
                bad(key, f"{self.tracker}'s motion samples have no search region to set")
        if recipe in ("memory", "motion") and self.search_center != "current":
            bad("search_center", f"{self.tracker}'s {recipe} samples support current only")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def recipe_value(self, key: str) -> Any:
        """The value of recipe item ``key``: the field when set, else the recipe's."""
        value = getattr(self, key)
        return RECIPES[self.recipe][key] if value is None else value

    def recipe_values(self) -> dict[str, Any]:
        """Every recipe item's value (see :data:`RECIPES`)."""
        return {key: self.recipe_value(key) for key in RECIPES["v2"]}

    def search_enlargement(self) -> tuple[float, float]:
        """``(scale, offset_m)`` of the search region in training and in the val env."""
        if self.tracker == "gpt" and self.recipe_value("gpt_search_region"):
            scale, offset_m = GPT_SEARCH_ENLARGEMENT
        else:
            scale, offset_m = SEARCH_SCALE, SEARCH_OFFSET_M
        if self.search_scale is not None:
            scale = float(self.search_scale)
        if self.search_offset_m is not None:
            offset_m = float(self.search_offset_m)
        return (scale, offset_m)

    def env_kwargs(self) -> dict[str, Any]:
        """The ``TrackingEnv`` options a tracker trained with this config must be evaluated
        with (its template composition and search region), as in training."""
        mode = (
            "first_and_previous_merged"
            if self.recipe_value("template_union")
            else ("first_and_previous")
        )
        return {"template_mode": mode, "search_enlargement": self.search_enlargement()}

    def env_options(self) -> dict[str, Any]:
        """The ``tracker.env_options`` a tracker trained with this config carries: all of
        :meth:`env_kwargs` when any differs from the env's default, else ``{}`` (recipe v1:
        nothing recorded, the tracker file is written exactly as before the options existed)."""
        kwargs = self.env_kwargs()
        defaults = default_env_options()
        if all(_same_option(kwargs[k], defaults[k]) for k in kwargs):
            return {}
        return kwargs

    def make_kwargs(self) -> dict:
        """Keyword arguments of ``trackers.make(self.tracker, ...)`` (BAT's backbone samples by
        farthest-point sampling when ``bat_fps`` is on, unless ``tracker_config`` says)."""
        kwargs = tracker_config(self.tracker, self.model_size, self.tracker_config)
        if self.tracker == "bat" and self.recipe_value("bat_fps"):
            backbone = dict(kwargs.get("backbone") or {})
            backbone.setdefault("sampling", "fps")
            kwargs["backbone"] = backbone
        return kwargs


def _drct_trainable(tracker_class: type) -> bool:
    """DRCT and -RD (:mod:`training.drct`) can train this tracker class: a matching tracker
    (``build_fusion``) or one that names its point backbone for DRCT (``drct_backbone``:
    MBPTrack). M2-Track is neither: its motion samples have no cloud-per-label layout that
    ``randomize_batch`` reads."""
    return hasattr(tracker_class, "build_fusion") or hasattr(tracker_class, "drct_backbone")


def _same_option(a: Any, b: Any) -> bool:
    """Equal env option values (a tuple and a list of the same numbers are the same)."""
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(float(x) == float(y) for x, y in zip(a, b, strict=True))
    return a == b


def checkpoint_tracker_kwargs(config: dict[str, Any]) -> dict[str, Any]:
    """The ``trackers.make`` kwargs of the tracker a training checkpoint's ``config`` trained
    (keys it lacks at their :data:`LEGACY_DEFAULTS`, else the defaults; unknown keys ignored),
    recipe items included (BAT's FPS)."""
    return _checkpoint_config(config).make_kwargs()


def checkpoint_env_options(config: dict[str, Any]) -> dict[str, Any]:
    """The ``tracker.env_options`` of the tracker a training checkpoint's ``config`` trained
    (:meth:`TrainConfig.env_options`; keys it lacks read as in
    :func:`checkpoint_tracker_kwargs`, so a checkpoint older than the recipes records none)."""
    return _checkpoint_config(config).env_options()


def _checkpoint_config(config: dict[str, Any]) -> TrainConfig:
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {k: v for k, v in {**LEGACY_DEFAULTS, **config}.items() if k in known}
    return TrainConfig(**values)


# Keys that may change between a run and its resumption (they do not change the result).
IDENTITY_EXEMPT = frozenset(
    {
        "epochs",
        "out",
        "num_workers",
        "num_threads",
        "progress",
        "logger",
        "device",
        "val_every",
        "val_max_tracklets",
        "val_max_frames",
    }
)

_FIELDS = {f.name: f for f in dataclasses.fields(TrainConfig)}
_HINTS = typing.get_type_hints(TrainConfig)


def _check_type(key: str, value: Any) -> Any:
    """Coerce ``value`` to the field's type or raise a one-line reason."""
    return coerce(_HINTS[key], value)


def coerce(hint: Any, value: Any) -> Any:
    """``value`` (from YAML or ``--set``) as a config field of type ``hint`` (``int``,
    ``float``, ``str``, ``bool``, ``dict``, or one of them ``| None``); ``TypeError`` with a
    one-line reason otherwise (the config systems of ``train`` and ``finetune`` share it)."""
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
        if isinstance(value, str):
            # YAML 1.1 (PyYAML) reads 1e-8 (no dot) as a string: take it as the number it is
            try:
                return float(value)
            except ValueError:
                raise TypeError("must be a number") from None
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
    path = Path(path)
    try:
        values = read_yaml_mapping(path)
    except ValueError as exc:
        raise ConfigError(f"config file {exc}") from None
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
