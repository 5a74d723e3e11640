"""`pointtrack finetune`: RL fine-tuning of a pretrained tracker (stable-baselines3 PPO).

Examples::

    pointtrack finetune --tracker p2b-kitti1-u --algo ppo --timesteps 4096 --num-envs 4 \\
        --out runs/ft-p2b
    pointtrack finetune --tracker p2b-kitti1-u --timesteps 8192 --num-envs 4 --out runs/ft-p2b \\
        --resume
    pointtrack eval --tracker runs/ft-p2b/tracker.safetensors --preset default --setting kitti-1

``--algo ppo`` trains the tracker itself (``training.rl.TrackerPolicy``) on the train split's
observed categories and writes ``OUT/tracker.safetensors``, an ordinary tracker checkpoint;
``--algo residual`` trains a small residual policy on top of the frozen tracker and writes
``OUT/residual.safetensors`` (also accepted by ``pointtrack eval --tracker``). See
:mod:`training.finetune` and docs/rl.md.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags (defaults: :class:`training.finetune.FinetuneConfig`)."""
    from training.finetune import ALGOS, FinetuneConfig
    from training.rl import ACTION_MODES, CRITICS, TRAIN_PARTS

    d = FinetuneConfig()
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    add = parser.add_argument
    add(
        "--tracker",
        default=d.tracker,
        help="a shipped checkpoint name or a tracker checkpoint file",
    )
    add(
        "--algo",
        default=d.algo,
        choices=ALGOS,
        help="ppo: train the tracker as the policy; residual: a residual MLP on the frozen one",
    )
    add("--setting", default=d.setting, help="its observed categories are trained on")
    add("--preset", default=d.preset, help="synthetic world preset (tiny, small, default)")
    add("--sensor", default=d.sensor, help="synthetic LiDAR profile")
    add(
        "--world-seed",
        dest="world_seed",
        type=int,
        default=d.world_seed,
        help="synthetic world seed (its train split is used)",
    )
    add(
        "--data-root",
        dest="data_root",
        default=None,
        help="a KITTI-layout root instead of a synthetic world",
    )
    add("--reward", default=d.reward, help="the env's reward")
    add(
        "--clip-length",
        dest="clip_length",
        type=int,
        default=d.clip_length,
        help="steps per training episode (TimeLimit; 0: whole tracklets)",
    )
    add("--timesteps", type=int, default=d.timesteps, help="total env steps (all sub-envs)")
    add(
        "--num-envs",
        dest="num_envs",
        type=int,
        default=d.num_envs,
        help="sub-envs stepped together (one batched tracker forward per step)",
    )
    add(
        "--n-steps",
        dest="n_steps",
        type=int,
        default=d.n_steps,
        help="steps per sub-env between PPO updates",
    )
    add("--batch-size", dest="batch_size", type=int, default=d.batch_size, help="PPO minibatch")
    add("--n-epochs", dest="n_epochs", type=int, default=d.n_epochs, help="PPO epochs per update")
    add("--lr", type=float, default=d.lr, help="learning rate of the value head and log-std")
    add(
        "--tracker-lr",
        dest="tracker_lr",
        type=float,
        default=d.tracker_lr,
        help="learning rate of the tracker's trained parts",
    )
    add(
        "--train-parts",
        dest="train_parts",
        default=d.train_parts,
        choices=TRAIN_PARTS,
        help="which tracker parts train",
    )
    add(
        "--action-mode",
        dest="action_mode",
        default=d.action_mode,
        choices=ACTION_MODES,
        help="policy mean: the best proposal, or the score-weighted mean of the proposals",
    )
    add(
        "--critic",
        default=d.critic,
        choices=CRITICS,
        help="value head on the tracker's pooled fused features, or a separate small PointNet",
    )
    add(
        "--log-std-init",
        dest="log_std_init",
        type=float,
        default=d.log_std_init,
        help="initial log standard deviation (normalised action units)",
    )
    add(
        "--warmup-rollouts",
        dest="warmup_rollouts",
        type=int,
        default=d.warmup_rollouts,
        help="first updates train the critic only (actor frozen)",
    )
    add(
        "--target-kl",
        dest="target_kl",
        type=float,
        default=d.target_kl,
        help="stop an update's epochs when approx_kl exceeds 1.5x this",
    )
    add("--clip-range", dest="clip_range", type=float, default=d.clip_range, help="PPO ratio clip")
    add(
        "--max-grad-norm",
        dest="max_grad_norm",
        type=float,
        default=d.max_grad_norm,
        help="gradient clipping (global norm)",
    )
    add("--gamma", type=float, default=d.gamma, help="discount")
    add("--gae-lambda", dest="gae_lambda", type=float, default=d.gae_lambda, help="GAE lambda")
    add("--ent-coef", dest="ent_coef", type=float, default=d.ent_coef, help="entropy bonus")
    add("--seed", type=int, default=d.seed, help="seed of PPO and the episode draws")
    add("--device", default=d.device, help="cpu or cuda[:N]")
    add("--threads", type=int, default=d.threads, help="torch.set_num_threads")
    add(
        "--save-every",
        dest="save_every",
        type=int,
        default=d.save_every,
        help="updates between resume checkpoints (OUT/state.safetensors)",
    )
    add(
        "--snapshot-every",
        dest="snapshot_every",
        type=int,
        default=d.snapshot_every,
        help="updates between tracker snapshots in OUT/snapshots (0: none)",
    )
    add(
        "--val-max-tracklets",
        dest="val_max_tracklets",
        type=int,
        default=d.val_max_tracklets,
        help="quick val check of base vs fine-tuned on this many tracklets (must be >= 1)",
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
