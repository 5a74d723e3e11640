"""What a training run is built from when the caller gives nothing else: the tracker
(:func:`default_model_factory`), the training samples (:func:`default_train_data`, by the
tracker's sample recipe) and the validation function (:func:`default_val_fn`: OPE on the val
split, observed categories only); the checks a run passes before anything is built
(:func:`check_run_dir`, :func:`check_device`); and :class:`TrainingError`. Used by
:class:`training.pretrain.Trainer`, which re-exports these names.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from training.config import TrainConfig
from training.rundir import TRAIN_LAYOUT, RunDirError, prepare_run_dir

__all__ = [
    "LOSS_ONLY_HEAD_FIELDS",
    "SAMPLE_RECIPE_KEYS",
    "TrainingError",
    "architecture_config",
    "check_device",
    "check_run_dir",
    "default_model_factory",
    "default_train_data",
    "default_val_fn",
    "kaiming_init",
]


class TrainingError(RuntimeError):
    """A run that cannot start or continue (bad resume, non-finite loss, no data)."""


def default_model_factory(cfg: TrainConfig) -> torch.nn.Module:
    import trackers

    model = trackers.make(cfg.tracker, **cfg.make_kwargs())
    if cfg.recipe_value("init") == "kaiming":
        if cfg.model_size == "slim":
            warnings.warn(
                "init='kaiming' (recipe v2) kept slim P2B at the floor for 6,400 samples in "
                "the ablation of docs/recipe.md, where torch's default init trained; add "
                "--set init=default unless you are measuring that",
                UserWarning,
                stacklevel=2,
            )
        kaiming_init(model)
    return model


def kaiming_init(model: torch.nn.Module) -> None:
    """Kaiming-normal weights (fan in, ReLU gain) and zero biases for every linear and
    convolution layer (recipe v2: Open3DSOT's initialisation), from torch's global generator
    (seeded by the trainer)."""
    for module in model.modules():
        if isinstance(module, torch.nn.Linear | torch.nn.Conv1d | torch.nn.Conv2d):
            torch.nn.init.kaiming_normal_(module.weight)
            if module.bias is not None:
                torch.nn.init.zeros_(module.bias)


LOSS_ONLY_HEAD_FIELDS = (
    "positive_radius",
    "negative_radius",
    "positive_fraction",
    "objectness_pos_weight",
)
"""The ``HeadConfig`` fields that only label and weigh the training loss."""


def architecture_config(config: dict[str, Any]) -> dict[str, Any]:
    """A tracker config (``trackers.config.config_to_dict``) without what only shapes the
    loss (``loss_weights``, :data:`LOSS_ONLY_HEAD_FIELDS`): weights move between two trackers
    whose architecture configs are equal (``init_weights`` may start a run with other labels)."""
    kept = {k: v for k, v in config.items() if k != "loss_weights"}
    if isinstance(kept.get("head"), dict):
        kept["head"] = {k: v for k, v in kept["head"].items() if k not in LOSS_ONLY_HEAD_FIELDS}
    return kept


def _config_tracklets(cfg: TrainConfig, split: str) -> tuple[list, str]:
    """The observed-category tracklets of ``split`` of the data ``cfg`` names, and its root."""
    from training.samples import load_tracklets

    tracklets, _, root = load_tracklets(
        cfg.dataset,
        split,
        setting=cfg.setting,
        category=cfg.category,
        preset=cfg.preset,
        sensor=cfg.sensor,
        world_seed=cfg.world_seed,
        data_root=cfg.data_root,
        version=cfg.nuscenes_version,
        nuscenes_frame=cfg.nuscenes_frame,
    )
    return tracklets, root


def default_train_data(cfg: TrainConfig):
    import trackers
    from training.samples import TrackingSamples

    tracklets, root = _config_tracklets(cfg, "train")
    sample_recipe = getattr(trackers.tracker_class(cfg.tracker), "sample_recipe", None)
    if sample_recipe in ("memory", "motion"):
        if cfg.size_jitter > 0:
            raise TrainingError(
                f"size_jitter={cfg.size_jitter}: the {sample_recipe} samples of "
                f"{cfg.tracker} have no object resizing; use 0"
            )
        if sample_recipe == "memory":
            from training.memory_samples import MemorySamples

            data = MemorySamples(
                tracklets,
                candidates_per_frame=cfg.candidates_per_frame,
                seed=cfg.seed,
                search_enlargement=cfg.search_enlargement(),
            )
        else:
            from training.motion_samples import MotionSamples

            data = MotionSamples(
                tracklets, candidates_per_frame=cfg.candidates_per_frame, seed=cfg.seed
            )
        data.root = str(root)
        return data
    recipe = cfg.recipe_values()
    data = TrackingSamples(
        tracklets,
        candidates_per_frame=cfg.candidates_per_frame,
        seed=cfg.seed,
        size_jitter=cfg.size_jitter,
        search_enlargement=cfg.search_enlargement(),
        search_center=cfg.search_center,
        **{k: recipe[k] for k in SAMPLE_RECIPE_KEYS},
    )
    data.root = str(root)  # logged: a synthetic world's folder name carries its generator hash
    return data


SAMPLE_RECIPE_KEYS = (
    "zero_offset_candidate",
    "min_crop_points",
    "template_union",
    "frame0_samples",
    "limit_box",
)
"""The recipe items that are ``TrackingSamples`` options."""


def _truncate(tracklet, max_frames: int | None):
    if max_frames is None or len(tracklet) <= max_frames:
        return tracklet
    return dataclasses.replace(
        tracklet, frames=tracklet.frames[:max_frames], boxes=tracklet.boxes[:max_frames]
    )


def default_val_fn(cfg: TrainConfig) -> Callable[[torch.nn.Module], dict[str, float]]:
    """OPE on the val split, observed categories only, via ``training.evaluate.evaluate``."""
    from envs.data import class_specific, get_setting
    from envs.tracking_env import make_tracking_env
    from training.evaluate import evaluate, observation_keys_for

    st = class_specific(cfg.category) if cfg.category else get_setting(cfg.setting)
    # observed categories only: model selection never sees the unseen ones
    tracklets, _ = _config_tracklets(cfg, "val")
    if cfg.val_max_tracklets is not None and len(tracklets) > cfg.val_max_tracklets:
        pick = np.linspace(0, len(tracklets) - 1, cfg.val_max_tracklets).round().astype(int)
        tracklets = [tracklets[i] for i in sorted(set(pick.tolist()))]
    tracklets = [_truncate(tr, cfg.val_max_frames) for tr in tracklets]

    holder = _Tracklets(tracklets)
    n_envs = max(1, min(8, len(tracklets)))

    def run(model: torch.nn.Module) -> dict[str, float]:
        import gymnasium as gym

        def make_env():
            return make_tracking_env(
                holder,
                setting=st,
                categories=st.observed,
                sampling="sequential",
                observation_keys=observation_keys_for([model]),
                **cfg.env_kwargs(),
            )

        env = gym.vector.SyncVectorEnv([make_env] * n_envs) if n_envs > 1 else make_env()
        try:
            report = evaluate(model, env, seed=cfg.seed)
        finally:
            env.close()
        return _summarise_report(report)

    return run


class _Tracklets:
    """A minimal dataset (``.tracklets``) for the val env."""

    def __init__(self, tracklets):
        self.tracklets = tracklets


def _summarise_report(report: dict[str, Any]) -> dict[str, float]:
    """Mean Success / Precision of an :func:`training.evaluate.evaluate` report."""
    return {
        "success": float(report["mean"]["success"]),
        "precision": float(report["mean"]["precision"]),
    }


def check_run_dir(out: str | Path, resume: bool) -> Path | None:
    """Decide what a run into ``out`` does before anything is built: the ``last.pt`` to resume
    from, or ``None`` for a run from the beginning (:func:`training.rundir.prepare_run_dir`
    with :data:`~training.rundir.TRAIN_LAYOUT`: a fresh run refuses a directory holding a run,
    ``resume=True`` one holding nothing, and a directory killed in its first epoch (a
    ``config.yaml``, no ``last.pt``) starts again). Raises :class:`TrainingError`."""
    try:
        return prepare_run_dir(out, TRAIN_LAYOUT, resume=resume)
    except RunDirError as exc:
        raise TrainingError(str(exc)) from None


def check_device(device: str) -> None:
    """Refuse a CUDA device when CUDA is unavailable or the index does not exist."""
    if not device.startswith("cuda"):
        return
    if not torch.cuda.is_available():
        raise TrainingError(f"device {device!r}: CUDA is not available on this machine")
    index, count = torch.device(device).index, torch.cuda.device_count()
    if index is not None and index >= count:
        raise TrainingError(f"device {device!r}: only {count} CUDA device(s) here")
