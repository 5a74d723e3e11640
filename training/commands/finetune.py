"""`pointtrack finetune`: PPO fine-tuning of a pretrained tracker (a residual policy on top of it).

Example::

    pointtrack finetune --tracker p2b-kitti1-u --preset small --timesteps 4096 --out runs/ft

Trains on the train split (random tracklets, observed categories of the setting), then scores
the base tracker and the fine-tuned one on the val split and prints both. See
:mod:`training.finetune` for the design.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    parser.add_argument("--tracker", required=False, default="p2b-kitti1-u",
                        help="a shipped checkpoint name or a tracker file (default p2b-kitti1-u)")
    parser.add_argument("--setting", default="kitti-1")
    parser.add_argument("--preset", default="small", help="synthetic world preset")
    parser.add_argument("--data-root", dest="data_root", help="a KITTI-layout root instead")
    parser.add_argument("--timesteps", type=int, default=4096)
    parser.add_argument("--n-steps", dest="n_steps", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--val-max-tracklets", dest="val_max_tracklets", type=int, default=8)
    parser.add_argument("--out", default="runs/finetune")


def run(args: argparse.Namespace) -> int:
    if args.timesteps < 1 or args.n_steps < 2:
        raise SystemExit("pointtrack finetune: --timesteps must be >= 1 and --n-steps >= 2")
    import torch

    from envs.data import KittiTracking, get_setting
    from envs.tracking_env import TrackingEnv
    from training.evaluate import evaluate
    from training.finetune import finetune

    torch.set_num_threads(1)
    try:
        setting = get_setting(args.setting)
    except ValueError as exc:
        raise SystemExit(f"pointtrack finetune: {exc}") from None
    if args.data_root:
        root = args.data_root
    else:
        from envs.synthetic import ensure_world

        root = str(ensure_world(preset=args.preset))
    train = KittiTracking(root, "train", list(setting.observed))
    val = KittiTracking(root, "val", list(setting.observed))

    def make_train_env():
        return TrackingEnv(train, setting=setting, categories=setting.observed, sampling="random")

    tuned = finetune(args.tracker, make_train_env, total_timesteps=args.timesteps,
                     out=args.out, seed=args.seed, n_steps=args.n_steps, verbose=1)
    subset = list(range(min(args.val_max_tracklets, len(val.tracklets))))
    for name, tracker in (("base", tuned.base), ("finetuned", tuned)):
        env = TrackingEnv(val, setting=setting, categories=setting.observed)
        rep = evaluate(tracker, env, tracklets=subset, seed=args.seed)
        print(f"{name}: val success {rep['mean']['success']:.2f} "
              f"precision {rep['mean']['precision']:.2f} ({rep['frames']} frames)")
    print(f"saved {args.out}/ppo.zip")
    return 0
