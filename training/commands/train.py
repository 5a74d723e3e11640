"""`pointtrack train`: pretrain P2B / BAT / GPT (plain -U, decorrelation -W, SAM -S; DRCT).

Examples::

    pointtrack train --tracker p2b --setting kitti-1 --weighting decorrelation \\
        --dataset synthetic --preset default --epochs 36 --out runs/p2b-w
    pointtrack train --config my.yaml --set iters_per_epoch=200 --out runs/x --resume
    torchrun --nproc_per_node 2 -m training.cli train --tracker bat --out runs/bat-ddp

Precedence: built-in defaults < ``--config FILE`` (YAML, keys of ``training.config.TrainConfig``;
with ``--resume`` and no ``--config``, ``OUT/config.yaml``) < the flags below < ``--set
KEY=VALUE``. Flags left out take the config's value. Everything is validated, and ``--resume`` /
an existing ``--out`` / ``--device`` are checked, before any data is built.
"""

from __future__ import annotations

import argparse
import dataclasses

# flags whose destination is not the config key of the same name; every other flag whose
# destination is a TrainConfig field sets that field (so no flag can be silently dropped)
_RENAMED = {"threads": "num_threads"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    import trackers
    from training.commands.eval import add_nuscenes_frame_argument
    from training.config import SEARCH_CENTERS

    parser.add_argument(
        "--tracker", choices=trackers.available("learned"), help="the model to train"
    )
    parser.add_argument(
        "--setting", help="class-agnostic setting, e.g. kitti-1 (observed categories are trained)"
    )
    parser.add_argument("--category", help="class-specific mode: train on this category only")
    sizes = sorted(
        {s for n in trackers.available("learned") for s in trackers.tracker_class(n).sizes}
    )
    parser.add_argument(
        "--model-size",
        dest="model_size",
        choices=sizes,
        help="tracker widths: the papers' (default), slim (CPU training) or, for MBPTrack, light "
        "(slim with less per-frame work)",
    )
    parser.add_argument(
        "--weighting",
        choices=("none", "decorrelation", "sam"),
        help="none (-U), decorrelation (-W), sam (-S)",
    )
    parser.add_argument(
        "--dataset",
        choices=("synthetic", "kitti", "nuscenes"),
        help="synthetic world (generated once into the cache), a KITTI root or "
        "a nuScenes root (--data-root)",
    )
    parser.add_argument(
        "--version",
        dest="nuscenes_version",
        help="--dataset nuscenes: table folder (v1.0-trainval under --data-root, "
        "else v1.0-mini, the synthetic world in nuScenes layout)",
    )
    add_nuscenes_frame_argument(parser)
    parser.add_argument(
        "--drct",
        action="store_true",
        default=None,
        help="DRCT: dual-branch training with domain randomisation and local "
        "geometric contrast (training.drct; combinable with --weighting; "
        "drct_* config keys via --set)",
    )
    parser.add_argument(
        "--drct-variant",
        dest="drct_variant",
        choices=("asymmetric", "siamese"),
        help="asymmetric (DRCT: auxiliary copy with an extra FFN) or siamese "
        "(shared parameters, the paper's Fig. 7 ablation)",
    )
    parser.add_argument(
        "--domain-randomize",
        dest="domain_randomize",
        action="store_true",
        default=None,
        help="the -RD control: plain training on domain-randomised samples (dr_* config keys)",
    )
    parser.add_argument(
        "--preset",
        help="world preset (tiny, small, default; KITTI motion: tiny-km, small-km, default-km)",
    )
    parser.add_argument("--sensor", help="synthetic LiDAR profile (hdl64, hdl32)")
    parser.add_argument("--data-root", dest="data_root", help="KITTI tracking root")
    parser.add_argument(
        "--world-seed", dest="world_seed", type=int, help="seed of the synthetic training world"
    )
    parser.add_argument("--epochs", type=int, help="epochs to train")
    parser.add_argument("--batch-size", dest="batch_size", type=int, help="samples per step")
    parser.add_argument("--lr", type=float, help="Adam learning rate")
    parser.add_argument(
        "--iters-per-epoch",
        dest="iters_per_epoch",
        type=int,
        help="cap each epoch at this many batches (a fresh random subset)",
    )
    parser.add_argument(
        "--candidates-per-frame",
        dest="candidates_per_frame",
        type=int,
        help="search-area samples drawn per labelled frame",
    )
    parser.add_argument(
        "--size-jitter",
        dest="size_jitter",
        type=float,
        metavar="A",
        help="resize each sample's object by U(1-A, 1+A) per axis (default 0)",
    )
    parser.add_argument(
        "--search-scale",
        dest="search_scale",
        type=float,
        help="search region: the previous box scaled by this (default the tracker's, 1.25)",
    )
    parser.add_argument(
        "--search-offset",
        dest="search_offset_m",
        type=float,
        metavar="M",
        help="search region: plus M metres a side (default the tracker's, 2); recorded in the "
        "tracker file, so eval uses the same region",
    )
    parser.add_argument(
        "--search-center",
        dest="search_center",
        choices=SEARCH_CENTERS,
        help="training cuts the search region around the jittered current box (default) or "
        "the previous frame's (keeps the target's move: frames far apart, e.g. 2 Hz)",
    )
    parser.add_argument(
        "--ema-decay",
        dest="ema_decay",
        type=float,
        metavar="D",
        help="validate and export an exponential moving average of the weights "
        "with this decay per step (default 0 = off)",
    )
    parser.add_argument("--seed", type=int, help="seed of every random draw of the run")
    parser.add_argument(
        "--init-weights",
        dest="init_weights",
        metavar="CHECKPOINT",
        help="start from these tracker weights (a .safetensors/.pt file or a "
        "shipped name such as p2b-kitti1-u); fresh optimizer and schedule",
    )
    parser.add_argument("--out", help="run directory (checkpoints, logs)")
    parser.add_argument(
        "--num-workers", dest="num_workers", type=int, help="DataLoader worker processes"
    )
    parser.add_argument("--threads", type=int, help="torch.set_num_threads")
    parser.add_argument("--device", help="cpu or cuda[:N]")
    parser.add_argument(
        "--val-max-tracklets",
        dest="val_max_tracklets",
        type=int,
        help="validate on at most this many val tracklets (spread evenly)",
    )
    parser.add_argument(
        "--val-max-frames",
        dest="val_max_frames",
        type=int,
        help="truncate each val tracklet to this many frames",
    )
    parser.add_argument("--config", help="YAML file of config keys")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any config key (repeatable), e.g. --set decor_penalty=0.2",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue OUT/last.pt; without --config the run's own "
        "OUT/config.yaml is the base config",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--logger",
        metavar="OUTPUTS",
        help="scalar outputs in OUT/logs: a comma list of csv, json, tensorboard (the tensorboard "
        "extra); view with tensorboard --logdir runs/",
    )
    parser.add_argument(
        "--export",
        metavar="FILE.safetensors",
        help="write the best (else last) weights with trackers.save",
    )
    _show_config_defaults(parser)


def _show_config_defaults(parser: argparse.ArgumentParser) -> None:
    """End each config flag's help with the config's default (the flags themselves default to
    "not given", so that --config and OUT/config.yaml can supply the value)."""
    from training.config import TrainConfig

    defaults = TrainConfig().to_dict()
    for action in parser._actions:
        key = _RENAMED.get(action.dest, action.dest)
        if key in defaults and action.help is not None:
            action.help += f" (config default: {defaults[key]!r})"


def build_config(args: argparse.Namespace):
    """The validated config of these arguments (raises ``ConfigError``)."""
    from pathlib import Path

    from training.config import ConfigError, TrainConfig, config_from_dict, load_config, parse_value

    if args.config:
        cfg = load_config(args.config)
    elif args.resume and args.out and (Path(args.out) / "config.yaml").is_file():
        cfg = load_config(Path(args.out) / "config.yaml")  # the run's own config
    else:
        cfg = TrainConfig()
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {
        _RENAMED.get(dest, dest): value
        for dest, value in vars(args).items()
        if value is not None and _RENAMED.get(dest, dest) in fields
    }
    if args.category and args.setting is None:
        values["setting"] = None
    if args.no_progress:
        values["progress"] = False
    for item in args.set:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        values[key.strip()] = parse_value(value)
    return config_from_dict(values, cfg)


def export(run_dir, path: str) -> None:
    """Write the run's best (else last) weights as a tracker file via ``trackers.save``."""
    from pathlib import Path

    import trackers
    from training.checkpoint import tracker_from_checkpoint

    run_dir = Path(run_dir)
    src = run_dir / "best.pt" if (run_dir / "best.pt").exists() else run_dir / "last.pt"
    trackers.save(tracker_from_checkpoint(src), path)
    print(f"exported {src} -> {path}")


def run(args: argparse.Namespace) -> int:
    from training.config import ConfigError

    try:
        cfg = build_config(args)
    except ConfigError as exc:
        raise SystemExit(f"pointtrack train: {exc}") from None
    from training.scalars import require_formats

    require_formats(cfg.logger)  # a missing tensorboard is one line before any data is built
    from training.pretrain import TrainingError, train

    try:
        result = train(cfg, resume=args.resume)
    except (TrainingError, ValueError) as exc:
        raise SystemExit(f"pointtrack train: {exc}") from None
    import os

    if int(os.environ.get("RANK", "0")) == 0:
        best = result.best_val
        print(
            f"done: {result.epochs_done} epochs, {result.steps} steps, {result.wall_s:.0f} s, "
            f"{result.samples_per_s:.1f} samples/s; best val "
            + (
                f"success {best['success']:.2f} precision {best['precision']:.2f} "
                f"(epoch {result.best_epoch})"
                if best
                else "n/a"
            )
            + f"; checkpoints in {result.out}"
        )
        if args.export:
            export(result.out, args.export)
    return 0
