"""`pointtrack finetune`: RL fine-tuning of a pretrained tracker (stable-baselines3 PPO).

Examples::

    pointtrack finetune --tracker p2b-kitti1-u --algo ppo --timesteps 4096 --num-envs 4 \\
        --out runs/ft-p2b
    pointtrack finetune --tracker p2b-kitti1-u --timesteps 8192 --out runs/ft-p2b --resume
    pointtrack finetune --config hyperparams/group_ppo.yml --set group_size=16 \\
        --logger tensorboard,csv --out runs/ft-grp
    pointtrack eval --tracker runs/ft-p2b/tracker.safetensors --preset default --setting kitti-1

``--algo ppo`` trains the tracker itself (``training.rl.TrackerPolicy``) on the train split's
observed categories and writes ``OUT/tracker.safetensors``, an ordinary tracker checkpoint;
``--algo group`` trains the same policy from ``--group-size`` sampled actions per state
(``training.rl.GroupPPO``); ``--algo residual`` trains a small residual policy on top of the
frozen tracker and writes ``OUT/residual.safetensors`` (also accepted by
``pointtrack eval --tracker``). See :mod:`training.rl.run` and docs/rl.md.

Config precedence: :class:`~training.rl.config.FinetuneConfig`'s defaults < (with ``--resume``)
the run's saved ``OUT/config.json`` < ``--config FILE.yml`` (an RL Zoo-style YAML mapping of
config keys) < the flags given < ``--set key=value``. Only what the user gave counts: on
``--resume`` a flag given with the saved value continues the run, one given with another value
is refused (except the resumable ones). Everything is validated before any work; the resolved
config is saved as ``OUT/config.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path
from typing import Any

from training.config import parse_value
from training.rl.config import (
    ALGOS,
    BASELINES,
    LOGGER_FORMATS,
    MAX_GROUP_SIZE,
    FinetuneConfig,
    FinetuneError,
    config_from_values,
    read_hyperparams,
)
from training.rl.policy import ACTION_MODES, CRITICS, TRAIN_PARTS
from training.rl.run import finetune


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags. A config flag left out is absent from the parsed
    namespace (``argparse.SUPPRESS``), so :func:`build_config` knows what the user gave; its
    help names :class:`FinetuneConfig`'s default."""
    d = FinetuneConfig()
    add = parser.add_argument

    def config_flag(name: str, help: str, **kwargs: Any) -> None:
        """``--name`` sets the config field ``name`` (dashes for underscores); the type of a
        number comes from :class:`FinetuneConfig`."""
        dest = name.replace("-", "_")
        default = getattr(d, dest)
        if isinstance(default, int | float) and not isinstance(default, bool):
            kwargs["type"] = type(default)
        add(
            f"--{name}",
            dest=dest,
            default=argparse.SUPPRESS,
            help=f"{help} (default: {default!r})",
            **kwargs,
        )

    config_flag("tracker", "a shipped checkpoint name, a tracker file or a run's best.pt")
    config_flag(
        "algo",
        "ppo: train the tracker as the policy; group: the same with --group-size sampled "
        "actions per state (one-step rewards, no critic); residual: a residual MLP on the "
        "frozen one",
        choices=ALGOS,
    )
    config_flag("setting", "its observed categories are trained on")
    config_flag(
        "preset",
        "world preset (tiny, small, default; KITTI motion: tiny-km, small-km, default-km)",
    )
    config_flag("sensor", "synthetic LiDAR profile")
    config_flag("world-seed", "synthetic world seed (its train split is used)")
    config_flag("data-root", "a KITTI-layout root instead of a synthetic world")
    config_flag("reward", "the env's reward")
    config_flag("clip-length", "steps per training episode (TimeLimit; 0: whole tracklets)")
    config_flag("timesteps", "total env steps (all sub-envs)")
    config_flag("num-envs", "sub-envs stepped together (one batched tracker forward per step)")
    config_flag("n-steps", "steps per sub-env between PPO updates")
    config_flag("batch-size", "PPO minibatch")
    config_flag("n-epochs", "PPO epochs per update")
    config_flag("lr", "learning rate of the value head and log-std")
    config_flag("tracker-lr", "learning rate of the tracker's trained parts")
    config_flag("train-parts", "which tracker parts train", choices=TRAIN_PARTS)
    config_flag(
        "action-mode",
        "policy mean: the best proposal, or the score-weighted mean of the proposals",
        choices=ACTION_MODES,
    )
    config_flag(
        "critic",
        "value head on the tracker's pooled fused features, or a separate small PointNet",
        choices=CRITICS,
    )
    config_flag(
        "baseline",
        "advantage baseline: the learned critic, or the reward of the policy's mean action at "
        "the same state (self_critical; needs --gamma 0)",
        choices=BASELINES,
    )
    config_flag(
        "group-size", f"--algo group: sampled actions scored per state (<= {MAX_GROUP_SIZE})"
    )
    config_flag("log-std-init", "initial log standard deviation (normalised action units)")
    config_flag("warmup-rollouts", "first updates train the critic only (actor frozen)")
    config_flag("target-kl", "stop an update's epochs when approx_kl exceeds 1.5x this")
    config_flag("clip-range", "PPO ratio clip")
    config_flag("max-grad-norm", "gradient clipping (global norm)")
    config_flag("gamma", "discount")
    config_flag("gae-lambda", "GAE lambda")
    config_flag("ent-coef", "entropy bonus")
    config_flag("seed", "seed of PPO and the episode draws")
    config_flag("device", "cpu or cuda[:N]")
    config_flag("threads", "torch threads (None: every usable core)", type=int)
    config_flag("save-every", "updates between resume checkpoints (OUT/state.safetensors)")
    config_flag("snapshot-every", "updates between tracker snapshots in OUT/snapshots (0: none)")
    config_flag(
        "val-max-tracklets",
        "quick val check of base vs fine-tuned on this many tracklets (must be >= 1)",
    )
    config_flag(
        "logger",
        f"SB3 logger outputs under OUT/sb3, comma-separated: some of {', '.join(LOGGER_FORMATS)} "
        "(tensorboard --logdir OUT/sb3)",
    )
    add(
        "--untrained",
        dest="untrained",
        action="store_const",
        const=True,
        default=argparse.SUPPRESS,
        help="accept a learned tracker's bare name (fine-tune a random initialisation)",
    )
    add("--no-val", action="store_true", help="skip the quick val check")
    add("--config", help="RL Zoo-style YAML file of config keys (n_timesteps, n_envs, ... too)")
    add(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any config key (repeatable; beats the flags and --config), e.g. --set group_size=16",
    )
    add("--out", default="runs/finetune", help="run directory")
    add(
        "--resume",
        action="store_true",
        help="continue the run in --out with its saved config; flags given with other values "
        "must match it, except --timesteps (extends), --device, --threads, --save-every, "
        "--snapshot-every, --val-max-tracklets, --logger",
    )
    add("--overwrite", action="store_true", help="replace a run already in --out")
    add(
        "--allow-held-out",
        dest="allow_held_out",
        action="store_true",
        default=argparse.SUPPRESS,
        help="train in an env that serves a category the base file holds out (its setting's "
        "unseen ones; refused without this flag)",
    )
    add("--no-progress", action="store_true", help="no progress bar")


def _given(args: argparse.Namespace) -> dict[str, Any]:
    """The config values the user gave: ``--config`` < flags < ``--set`` (validated types)."""
    fields = {f.name for f in dataclasses.fields(FinetuneConfig)}
    values: dict[str, Any] = {}
    if args.config:
        values.update(read_hyperparams(args.config))
        config_from_values(values, where=f"config file {args.config}")  # its own errors first
    values.update({k: v for k, v in vars(args).items() if k in fields})
    if args.no_val:
        values["val_max_tracklets"] = 0
    for item in args.set:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise FinetuneError(f"--set {item!r}: expected KEY=VALUE")
        values[key.strip()] = parse_value(text) if text.strip() else ""
    return values


def build_config(args: argparse.Namespace) -> FinetuneConfig:
    """The validated :class:`~training.rl.config.FinetuneConfig` of these arguments (see the
    module docstring for the precedence)."""
    given = _given(args)
    if given.get("val_max_tracklets", 1) < 1 and not args.no_val:
        raise FinetuneError(
            f"val_max_tracklets must be >= 1, got {given['val_max_tracklets']} "
            f"(use --no-val to skip the val check)",
            ["val_max_tracklets"],
        )
    base = config_from_values(_saved_config(args.out)) if args.resume else None
    cfg = config_from_values(given, base)
    cfg.validate()
    return cfg


def _saved_config(out: str) -> dict[str, Any]:
    """The config of the run in ``out`` (``config.json``), {} when there is none (``finetune``
    then refuses the resume, naming the missing state)."""
    path = Path(out) / "config.json"
    if not path.is_file():
        return {}
    try:
        saved = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise FinetuneError(f"cannot read {path}: {exc}") from None
    fields = {f.name for f in dataclasses.fields(FinetuneConfig)}
    return {k: v for k, v in saved.items() if k in fields}


def flag_message(exc: FinetuneError) -> str:
    """``exc``'s message with each config field it names written as its flag."""
    message = str(exc)
    for name in exc.fields:
        flag = "--" + name.replace("_", "-")
        message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flag, message)
    return message


def _fail(message: str) -> SystemExit:
    """One line on stderr and exit status 2 (the CLI's convention for expected errors)."""
    print(f"pointtrack finetune: {message}", file=sys.stderr)
    return SystemExit(2)


def run(args: argparse.Namespace) -> int:
    try:
        cfg = build_config(args)
        result = finetune(
            cfg,
            args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            progress=not args.no_progress,
        )
    except FinetuneError as exc:
        raise _fail(flag_message(exc)) from None
    except OSError as exc:  # an unwritable --out, a missing data root
        raise _fail(f"{type(exc).__name__}: {exc}") from None
    print(
        f"done: {result.timesteps} steps, {result.updates} updates, {result.wall_s:.0f} s, "
        f"{result.steps_per_s:.2f} steps/s; wrote {result.tracker_path}"
    )
    return 0
