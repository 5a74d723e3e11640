"""`pointtrack finetune`: RL fine-tuning of a pretrained tracker (stable-baselines3 PPO).

Examples::

    pointtrack finetune --tracker p2b-kitti1-u --algo ppo --timesteps 4096 --num-envs 4 \\
        --out runs/ft-p2b
    pointtrack finetune --tracker p2b-kitti1-u --timesteps 8192 --num-envs 4 --out runs/ft-p2b \\
        --resume
    pointtrack eval --tracker runs/ft-p2b/tracker.safetensors --preset default --setting kitti-1

``--algo ppo`` trains the tracker itself (``training.rl.TrackerPolicy``) on the train split's
observed categories and writes ``OUT/tracker.safetensors``, an ordinary tracker checkpoint;
``--algo group`` trains the same policy from ``--group-size`` sampled actions per state
(``training.rl.GroupPPO``); ``--algo residual`` trains a small residual policy on top of the
frozen tracker and writes ``OUT/residual.safetensors`` (also accepted by
``pointtrack eval --tracker``). See
:mod:`training.finetune` and docs/rl.md.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags (defaults: :class:`training.finetune.FinetuneConfig`)."""
    from training.finetune import ALGOS, BASELINES, FinetuneConfig
    from training.rl import ACTION_MODES, CRITICS, TRAIN_PARTS

    d = FinetuneConfig()
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    add = parser.add_argument

    def config_flag(name: str, help: str, **kwargs) -> None:
        """``--name`` sets the config field ``name`` (dashes for underscores); its default,
        and the type of a number, come from :class:`FinetuneConfig`."""
        dest = name.replace("-", "_")
        default = getattr(d, dest)
        if isinstance(default, (int, float)):
            kwargs["type"] = type(default)
        add(f"--{name}", dest=dest, default=default, help=help, **kwargs)

    config_flag("tracker", "a shipped checkpoint name or a tracker checkpoint file")
    config_flag(
        "algo",
        "ppo: train the tracker as the policy; group: the same with --group-size sampled "
        "actions per state (one-step rewards, no critic); residual: a residual MLP on the "
        "frozen one",
        choices=ALGOS,
    )
    config_flag("setting", "its observed categories are trained on")
    config_flag("preset", "synthetic world preset (tiny, small, default)")
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
    config_flag("group-size", "--algo group: sampled actions scored per state")
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
    config_flag("threads", "torch.set_num_threads")
    config_flag("save-every", "updates between resume checkpoints (OUT/state.safetensors)")
    config_flag("snapshot-every", "updates between tracker snapshots in OUT/snapshots (0: none)")
    config_flag(
        "val-max-tracklets",
        "quick val check of base vs fine-tuned on this many tracklets (must be >= 1)",
    )
    add("--no-val", action="store_true", help="skip the quick val check")
    add("--out", default="runs/finetune", help="run directory")
    add(
        "--resume",
        action="store_true",
        help="continue the run in --out with its saved config; flags given with other values "
        "must match it, except --timesteps (extends), --device, --threads, --save-every, "
        "--snapshot-every, --val-max-tracklets",
    )
    add("--overwrite", action="store_true", help="replace a run already in --out")
    add(
        "--allow-held-out",
        action="store_true",
        help="train in an env that serves a category the base file holds out (its setting's "
        "unseen ones; refused without this flag)",
    )
    add("--no-progress", action="store_true", help="no progress bar")


def build_config(args: argparse.Namespace):
    """The validated :class:`~training.finetune.FinetuneConfig` of these arguments."""
    import dataclasses

    from training.finetune import FinetuneConfig, FinetuneError

    if args.val_max_tracklets < 1:
        raise FinetuneError(
            f"--val-max-tracklets must be >= 1, got {args.val_max_tracklets} "
            f"(use --no-val to skip the val check)"
        )
    fields = {f.name for f in dataclasses.fields(FinetuneConfig)}
    values = {k: v for k, v in vars(args).items() if k in fields}
    if args.no_val:
        values["val_max_tracklets"] = 0
    if args.resume:
        values = {**_saved_config(args.out, fields), **_changed(values)}
    cfg = FinetuneConfig(**values)
    cfg.validate()
    return cfg


def _saved_config(out: str, fields: set[str]) -> dict:
    """The config of the run in ``out`` (``config.json``), {} when there is none (``finetune``
    then refuses the resume, naming the missing state)."""
    import json
    from pathlib import Path

    path = Path(out) / "config.json"
    if not path.is_file():
        return {}
    try:
        saved = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        from training.finetune import FinetuneError

        raise FinetuneError(f"cannot read {path}: {exc}") from None
    return {k: v for k, v in saved.items() if k in fields}


def _changed(values: dict) -> dict:
    """The flags given with a value other than their default: on ``--resume`` the others come
    from the saved run, so ``--resume --out DIR`` alone continues DIR's run as configured."""
    from training.finetune import FinetuneConfig

    defaults = FinetuneConfig().to_dict()
    return {k: v for k, v in values.items() if v != defaults.get(k)}


def _fail(message: str) -> SystemExit:
    """One line on stderr and exit status 2 (the CLI's convention for expected errors)."""
    print(f"pointtrack finetune: {message}", file=sys.stderr)
    return SystemExit(2)


def run(args: argparse.Namespace) -> int:
    from training.finetune import FinetuneError, finetune

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
        raise _fail(str(exc)) from None
    except OSError as exc:  # an unwritable --out, a missing data root
        raise _fail(f"{type(exc).__name__}: {exc}") from None
    print(
        f"done: {result.timesteps} steps, {result.updates} updates, {result.wall_s:.0f} s, "
        f"{result.steps_per_s:.2f} steps/s; wrote {result.tracker_path}"
    )
    return 0
