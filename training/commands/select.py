"""`pointtrack select`: rank candidate checkpoints on validation data pooled over several worlds.

Example (the rule the shipped checkpoints are chosen by, ``docs/checkpoints.md``)::

    pointtrack select runs/a/best.pt runs/a/last.pt p2b-kitti1-w \\
        --setting kitti-1 --out runs/select-p2b-w

See :mod:`training.selection` for what is scored and why.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags (and ``--config`` / ``--set``, :mod:`training.argconfig`)."""
    from training.argconfig import add_config_arguments
    from training.commands.eval import add_nuscenes_frame_argument
    from training.selection import DEFAULT_PARTS

    add_config_arguments(parser)

    parser.add_argument(
        "candidates",
        nargs="+",
        metavar="CANDIDATE",
        help="training checkpoints (RUN/best.pt, RUN/last.pt: their validated weights), tracker "
        "files or shipped checkpoint names",
    )
    parser.add_argument(
        "--parts",
        nargs="+",
        default=[str(p) for p in DEFAULT_PARTS],
        metavar="WORLD:SPLIT",
        help="synthetic world splits pooled into one score (default: %(default)s)",
    )
    parser.add_argument(
        "--setting",
        default=None,
        help="its observed categories are scored (default: kitti-1; nuscenes-1 with --dataset "
        "nuscenes)",
    )
    parser.add_argument("--preset", default="default", help="synthetic preset (default: default)")
    parser.add_argument(
        "--sensor",
        default=None,
        help="synthetic sensor (default: hdl64; hdl32 with --dataset nuscenes)",
    )
    parser.add_argument(
        "--dataset",
        choices=("synthetic", "nuscenes"),
        default="synthetic",
        help="the worlds in KITTI layout (synthetic) or written in nuScenes layout (nuscenes)",
    )
    add_nuscenes_frame_argument(parser, default="lidar")
    parser.add_argument(
        "--train-world",
        type=int,
        default=0,
        metavar="SEED",
        help="world seed the candidates were trained on: its train and test splits are refused",
    )
    parser.add_argument("--eval-seed", type=int, default=0, help="seed of the point resampling")
    parser.add_argument(
        "--num-envs",
        type=int,
        default=1,
        help="sub-envs per evaluation (batched act; then --workers is 1)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="processes each evaluation shards its tracklets over, one torch thread each "
        "(default: every usable core; the scores do not depend on it)",
    )
    parser.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="write DIR/selection.json; per-part reports are kept in DIR/parts for reruns",
    )
    parser.add_argument(
        "--save",
        default=None,
        metavar="FILE.safetensors",
        help="write the first-ranked candidate as a tracker file whose provenance records this "
        "selection (the rule, the parts, every candidate's score)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument(
        "--logger",
        default=None,
        metavar="OUTPUTS",
        help="with --out: the ranking as scalars in DIR/logs (one step per rank, 0 = selected), "
        "a comma list of csv, json, tensorboard (default with --out: csv,json)",
    )


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from training.argconfig import save_options
    from training.evaluate import save_report
    from training.scalars import DEFAULT_FORMATS, require_formats
    from training.selection import (
        SelectionConfig,
        ValPart,
        format_ranking,
        ranking_uncertainty,
        score_candidates,
        tied_with_first,
    )

    try:
        from training.parallel import resolve_workers

        workers = 1 if args.num_envs > 1 and args.workers is None else args.workers
        nuscenes = args.dataset == "nuscenes"
        config = SelectionConfig(
            setting=args.setting or ("nuscenes-1" if nuscenes else "kitti-1"),
            preset=args.preset,
            sensor=args.sensor or ("hdl32" if nuscenes else "hdl64"),
            parts=tuple(ValPart.parse(p) for p in args.parts),
            train_world_seed=args.train_world,
            eval_seed=args.eval_seed,
            num_envs=args.num_envs,
            dataset=args.dataset,
            nuscenes_frame=args.nuscenes_frame,
            workers=resolve_workers(workers, "--workers"),
        )
        out = Path(args.out) if args.out else None
        if args.logger is not None and out is None:
            raise ValueError("--logger writes into --out DIR/logs: give --out")
        formats = require_formats(args.logger or DEFAULT_FORMATS)  # before any scoring
        rows = score_candidates(
            args.candidates,
            config,
            cache_dir=out / "parts" if out else None,
            progress=not args.no_progress,
        )
        uncertainty = ranking_uncertainty(rows)
    except ValueError as exc:
        raise SystemExit(f"pointtrack select: {exc}") from exc
    print(format_ranking(rows, uncertainty))
    tied = tied_with_first(rows)
    if tied:  # the resamples give a tie to the row listed first: no evidence either way
        print(
            f"tie: {rows[0]['candidate']} and {', '.join(tied)} pool exactly the same observed "
            f"Success ({rows[0]['success']:.2f}); {rows[0]['candidate']} is listed (and "
            "selected) first only because it was given first"
        )
    else:
        print(
            f"selected: {rows[0]['candidate']} (pooled observed Success "
            f"{rows[0]['success']:.2f}; ranked first in {uncertainty[0]['p_first']:.0%} of "
            "tracklet resamples)"
        )
    if out is not None:
        summary = {
            "config": {**vars(config), "parts": [str(p) for p in config.parts]},
            "ranking": [row | {"uncertainty": u} for row, u in zip(rows, uncertainty, strict=True)],
        }
        path = save_report(summary, out / "selection.json")
        log_ranking(rows, uncertainty, out / "logs", formats)
        save_options(args, out)
        print(f"wrote {path}, {out / 'config.yaml'} and {out / 'logs'}")
    if args.save:
        from training.selection import save_selected

        print(f"wrote {save_selected(rows, config, args.save)}")
    return 0


def log_ranking(
    rows: list[dict], uncertainty: list[dict], folder, formats: tuple[str, ...]
) -> None:
    """The ranking as ``select/...`` scalars (stable-baselines3's logger, :mod:`training.scalars`):
    one step per rank (0 = selected) with the candidate, its pooled and per-part Success /
    Precision and its share of first places over the tracklet resamples."""
    from training.scalars import log_record, open_scalar_logger

    logger = open_scalar_logger(folder, formats)
    for rank, (row, u) in enumerate(zip(rows, uncertainty, strict=True)):
        record = {"kind": "select", "step": rank, "candidate": row["candidate"]}
        record |= {k: row[k] for k in ("success", "precision", "frames")}
        record["p_first"] = u["p_first"]
        for part, scores in row["parts"].items():
            slug = part.replace(":", "_")
            record |= {f"{k}_w{slug}": scores[k] for k in ("success", "precision")}
        log_record(logger, record)
    logger.close()
