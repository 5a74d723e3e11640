"""`pointtrack eval`: run trackers step-wise through the environment and report OPE.

Example::

    pointtrack eval --tracker previous_box constant_velocity --dataset synthetic --preset small \\
        --setting kitti-1 --out runs/eval

The env is built by :func:`build_env` from the parsed arguments, so other commands (and the
weather option) can reuse or extend it with extra env keywords. Each tracker is evaluated with
the env options it records (``tracker.env_options``, e.g. recipe v2's merged template): one env
per distinct option set; an explicit ``--template-mode`` wins, and ``evaluate`` warns for a
tracker it contradicts (docs/recipe.md).

The tracklets are sharded over ``--workers`` processes (every usable core by default; the
results do not depend on it), ``--eval-seeds`` gives one report averaged over seeds, every
number gets a 90 % bootstrap interval over tracklets, an oracle ``--reference`` is marked, and
``--save-boxes`` writes every frame's boxes (docs/evaluation.md). Every flag is checked before
any tracker is loaded or directory made.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Any

from envs.data import check_setting_layout
from envs.data.nuscenes import SOT_SPLITS
from envs.tracking_env import TEMPLATE_MODES, make_tracking_env

#: the report, plots, weather tables and box files are written atomically (the boxes' result
#: folder renamed into place) and closed before ``run`` returns: the command line may skip the
#: interpreter's teardown (:func:`training.cli.entry`)
FAST_EXIT = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags (and ``--config`` / ``--set``, :mod:`training.argconfig`)."""
    from training.argconfig import add_config_arguments

    add_config_arguments(parser)
    parser.add_argument(
        "--tracker",
        nargs="+",
        default=["previous_box"],
        metavar="NAME_OR_PATH",
        help="tracker name(s) or checkpoint path(s) for trackers.load (default: previous_box)",
    )
    add_env_arguments(parser)
    parser.add_argument("--out", default=None, metavar="DIR", help="write JSON and PNG plots here")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="shard the tracklets (with --weather: the conditions) over N forked processes, "
        "one torch thread each; per-tracklet results do not depend on N (default: every usable "
        "core; 1 with --num-envs > 1 or --device cuda; more than the cores is clamped)",
    )
    parser.add_argument(
        "--device",
        default="cpu",
        help="cpu, or cuda[:N]: the trackers run there on the batched path "
        "(batch_invariant=False, --num-envs 32 unless given, one process); the report says so",
    )
    parser.add_argument(
        "--num-envs",
        type=int,
        default=None,
        help="run N sub-envs (SyncVectorEnv) so the tracker acts on batches (default 1; 32 "
        "with --device cuda)",
    )
    parser.add_argument(
        "--eval-seed",
        type=int,
        default=None,
        help="seed of the point resampling (per tracklet: results do not depend on --num-envs "
        "or --workers; default 0)",
    )
    parser.add_argument(
        "--eval-seeds",
        type=int,
        nargs="+",
        default=None,
        metavar="SEED",
        help="evaluate at each seed: one report with the mean and each seed's values",
    )
    parser.add_argument(
        "--max-tracklets",
        type=int,
        default=None,
        metavar="N",
        help="evaluate the first N only (N >= 1)",
    )
    parser.add_argument(
        "--save-boxes",
        action="store_true",
        help="with --out: write every frame's boxes (OUT/boxes/TRACKER.jsonl) and one result "
        "file per tracklet (OUT/boxes/TRACKER/seedS/SCENE_ID.txt); docs/evaluation.md",
    )
    parser.add_argument(
        "--untrained",
        action="store_true",
        help="allow a learned tracker's bare name (p2b, bat, gpt): a randomly initialised "
        "model seeded by --eval-seed (without this flag such a name is refused)",
    )
    parser.add_argument(
        "--strict",
        action="store_true",
        help="refuse, instead of warning, a tracker whose provenance says it trained or was "
        "selected on the data evaluated, or trained on a category the setting holds out",
    )
    parser.add_argument(
        "--network-alone",
        action="store_true",
        help="evaluate each learned tracker without the inference settings its file records "
        "(the still-target test and the re-ranking off): its network's best proposal; the "
        "report's eval block says so",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    # --weather, --weather-levels, --weather-seed, --no-analysis (training.robustness, issue 7)
    from training.robustness import add_weather_arguments

    add_weather_arguments(parser)


def add_nuscenes_frame_argument(
    parser: argparse.ArgumentParser, default: str | None = None
) -> None:
    """``--nuscenes-frame`` (dest ``nuscenes_frame``) of the commands that read nuScenes data."""
    from envs.data.nuscenes import NUSCENES_FRAMES

    parser.add_argument(
        "--nuscenes-frame",
        dest="nuscenes_frame",
        choices=NUSCENES_FRAMES,
        default=default,
        help="--dataset nuscenes: scans and boxes in each key frame's LiDAR frame (lidar, "
        "default) or in the scene's first key frame's, ego motion removed (scene)",
    )


def add_world_arguments(parser: argparse.ArgumentParser, split_help: str) -> None:
    """``--preset``, ``--sensor``, ``--seed`` (the synthetic world) and ``--split`` (help
    ``split_help``): the world flags of `eval` (and `render`, through :func:`add_env_arguments`)
    and `demo`."""
    parser.add_argument(
        "--preset",
        default="small",
        help="synthetic preset (tiny, small, default; KITTI motion: tiny-km, small-km, default-km)",
    )
    parser.add_argument("--sensor", default="hdl64", help="synthetic sensor (hdl64, hdl32)")
    parser.add_argument("--seed", type=int, default=0, help="synthetic world seed")
    parser.add_argument(
        "--split", default="test", choices=("train", "val", "test", "all"), help=split_help
    )


def add_env_arguments(parser: argparse.ArgumentParser) -> None:
    """The dataset / env flags of `eval` and `render`."""
    parser.add_argument(
        "--dataset",
        choices=("synthetic", "kitti", "nuscenes"),
        default="synthetic",
        help="a synthetic world (generated once into the cache), a KITTI root or a nuScenes root",
    )
    parser.add_argument(
        "--root",
        default=None,
        metavar="DIR",
        help="KITTI tracking root or a generated world (label_02/, calib/, velodyne/); needed "
        "with --dataset kitti. nuScenes dataroot (v1.0-*/, samples/) with --dataset nuscenes "
        "(without it: the synthetic world in nuScenes layout, --preset/--sensor/--seed)",
    )
    parser.add_argument(
        "--version",
        default=None,
        help="--dataset nuscenes: table folder (default v1.0-trainval with --root, else "
        "v1.0-mini); --split train/val/test read train_track/train_detect/val",
    )
    add_nuscenes_frame_argument(parser)
    add_world_arguments(parser, "scenes: train 0-16, val 17-18, test 19-20 (KITTI's split)")
    parser.add_argument(
        "--allow-missing-scenes",
        action="store_true",
        help="go on (with a warning listing them) when the root lacks label files of scenes "
        "the split names; without it that is an error",
    )
    parser.add_argument(
        "--setting",
        default=None,
        help="class-agnostic setting (kitti-1, kitti-2, nuscenes-1, nuscenes-2, "
        "class-specific:<Category>); default kitti-1 unless --categories",
    )
    parser.add_argument("--categories", nargs="+", default=None, help="restrict to categories")
    parser.add_argument(
        "--template-mode",
        default=None,
        choices=TEMPLATE_MODES,
        help="which earlier frames give the template points (default: the mode each tracker "
        "records, e.g. first_and_previous_merged for recipe v2, else first_and_previous; a "
        "mode that contradicts a tracker's is used, with a warning)",
    )
    parser.add_argument(
        "--reference",
        default="prediction",
        choices=("prediction", "previous_gt", "current_gt"),
        help="the box the search area is cut around (prediction: the honest closed loop)",
    )


def env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``TrackingEnv`` / factory keywords from the parsed arguments."""
    setting = args.setting
    if setting is None and not args.categories:
        setting = "nuscenes-1" if getattr(args, "dataset", None) == "nuscenes" else "kitti-1"
    return {
        "split": args.split,
        "setting": setting,
        "categories": args.categories,
        "reference": args.reference,
    } | ({} if args.template_mode is None else {"template_mode": args.template_mode})


def explicit_env_options(args: argparse.Namespace) -> dict[str, Any]:
    """The env options the user chose on the command line (``None``: not chosen), which win
    over the options a tracker records (``training.evaluate.env_option_groups``)."""
    return {"template_mode": getattr(args, "template_mode", None)}


def build_env(args: argparse.Namespace, **overrides: Any):
    """The :class:`~envs.tracking_env.TrackingEnv` the arguments describe; ``overrides`` (e.g.
    ``scan_transform=...``) go to the env."""
    kwargs = env_kwargs(args)
    kwargs.update(overrides)
    if args.dataset == "kitti" and not args.root:
        raise SystemExit("pointtrack eval: --dataset kitti needs --root DIR")
    if args.root:  # KITTI, a generated world, or a nuScenes dataroot
        source = "nuscenes" if args.dataset == "nuscenes" else "kitti"
        kwargs["root"] = args.root
        if source == "kitti" and getattr(args, "allow_missing_scenes", False):
            kwargs["allow_missing_scenes"] = True
    else:
        source = args.dataset
        kwargs.update(preset=args.preset, sensor=args.sensor, seed=args.seed)
    frame = getattr(args, "nuscenes_frame", None)
    if source == "nuscenes":
        kwargs.update(version=args.version, split=SOT_SPLITS[kwargs["split"]], frame=frame)
    elif frame is not None:
        raise SystemExit(
            f"pointtrack: --nuscenes-frame applies to --dataset nuscenes, not {source}"
        )
    return make_tracking_env(source, **kwargs)


def build_vector_env(args: argparse.Namespace, num_envs: int, **overrides: Any):
    """A ``SyncVectorEnv`` of ``num_envs`` copies of :func:`build_env` (the data are shared)."""
    import gymnasium as gym

    env = build_env(args, **overrides)
    return gym.vector.SyncVectorEnv([lambda e=env: e.clone() for _ in range(num_envs)])


@dataclass(frozen=True)
class EvalPlan:
    """How the evaluation runs, resolved from the flags before any work (``report["eval"]``).

    ``batch_invariant`` is the trackers' flag: ``True`` (one sample per forward) on the CPU,
    ``False`` (one batched forward) on a CUDA device, where batching is what pays."""

    seeds: tuple[int, ...]
    workers: int
    num_envs: int
    device: str
    batch_invariant: bool
    oracle: str | None
    network_alone: bool = False  # the learned trackers' inference settings off

    def describe(self) -> dict[str, Any]:
        """The plan as the report's JSON ``eval`` block."""
        return {
            "seeds": list(self.seeds),
            "workers": self.workers,
            "num_envs": self.num_envs,
            "device": self.device,
            "batch_invariant": self.batch_invariant,
            "oracle": self.oracle,
            "network_alone": self.network_alone,
        }


def run(args: argparse.Namespace) -> int:
    from training.evaluate import env_option_groups, observation_keys_for
    from training.provenance import eval_guard, mark_unseen

    plan = check_args(args)
    # every tracker before any data or evaluation, so a typo in the last one fails in a second
    loaded = load_trackers(args, plan)
    trained = eval_guard(loaded, args, env_kwargs(args)["setting"])  # leaks warned / --strict
    check_out(args)
    if getattr(args, "weather", None):
        return _run_weather(args, plan, loaded)
    if plan.device != "cpu":
        print(
            f"note: on {plan.device} the trackers run on the batched path "
            f"(batch_invariant=False, {plan.num_envs} sub-envs): per-tracklet results can "
            "differ in the last bits from the CPU's one-sample forwards",
            file=sys.stderr,
        )
    reports, boxes = {}, {}
    # one env per distinct option set the trackers record (e.g. recipe v2's template mode)
    for options, names in env_option_groups(loaded, explicit_env_options(args)):
        group = [loaded[name] for name in names]
        keys = observation_keys_for(group)  # e.g. M2-Track's previous frame
        env = (
            build_env(args, observation_keys=keys, **options)
            if plan.num_envs == 1
            else build_vector_env(args, plan.num_envs, observation_keys=keys, **options)
        )
        n = env.unwrapped.num_tracklets if plan.num_envs == 1 else env.get_attr("num_tracklets")[0]
        subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
        for name, tracker in zip(names, group, strict=True):
            reports[name], boxes[name] = _evaluate_seeds(args, plan, tracker, env, name, subset)
        env.close()
    reports = {name: reports[name] for name in loaded}  # the order of --tracker
    reports = mark_unseen(reports, trained)  # unseen: only what the file never trained on
    _print_and_save(args, reports, boxes, plan.workers)
    return 0


def _evaluate_seeds(args, plan: EvalPlan, tracker, env, name: str, subset):
    """One tracker at every eval seed -> (the combined report with intervals, ``{seed:
    per-tracklet boxes}`` when ``--save-boxes``)."""
    from envs.plotting import pyplot
    from training.evaluate import evaluate
    from training.intervals import add_intervals, combine_seeds

    runs = [
        evaluate(
            tracker,
            env,
            seed=seed,
            tracklets=subset,
            name=name,
            progress=not args.no_progress,
            workers=plan.workers,
            record_boxes=args.save_boxes,
            warm_up=pyplot if args.out else None,  # for the plots; imported once per process
        )
        for seed in plan.seeds
    ]
    boxes = {s: run.pop("boxes", None) for s, run in zip(plan.seeds, runs, strict=True)}
    report = add_intervals(combine_seeds(runs, plan.seeds))
    report["eval"] = plan.describe()
    return report, (boxes if args.save_boxes else None)


def _print_and_save(args, reports: dict[str, Any], boxes: dict[str, Any], workers: int) -> None:
    """Print the table; with ``--out``, the report, the plots (drawn over ``workers``
    processes) and (``--save-boxes``) boxes."""
    from training.evaluate import format_table, plot_curves, save_report

    print(format_table(reports))
    if not args.out:
        return
    from pathlib import Path

    out = Path(args.out)
    if args.save_boxes:
        from training.boxes import save_boxes

        for name, per_seed in boxes.items():
            path = save_boxes(per_seed, name, out / "boxes", observed=_observed(reports[name]))
            print(f"wrote {path} and the per-tracklet result files beside it")
    save_report(reports, out / "report.json")
    paths = plot_curves(reports, out, workers=workers)
    print(f"wrote {out / 'report.json'} and {', '.join(str(p) for p in paths)}")


def _observed(report: dict[str, Any]) -> dict[str, bool]:
    """``{category: observed}`` of a report (the box file records it per line)."""
    return {c: bool(e["observed"]) for c, e in report["categories"].items()}


def check_args(args: argparse.Namespace) -> EvalPlan:
    """Refuse every bad value before anything is loaded, built or written (``SystemExit`` with
    one line; the CLI turns it into exit status 2); returns the resolved :class:`EvalPlan`."""
    from training.intervals import check_seeds
    from training.parallel import resolve_workers
    from training.robustness import check_weather_arguments

    if args.num_envs is not None and args.num_envs < 1:
        raise SystemExit(f"pointtrack eval: --num-envs must be >= 1, got {args.num_envs}")
    if args.max_tracklets is not None and args.max_tracklets < 1:
        raise SystemExit(
            f"pointtrack eval: --max-tracklets must be >= 1, got "
            f"{args.max_tracklets} (leave it out to evaluate every tracklet)"
        )
    if args.eval_seed is not None and args.eval_seeds is not None:
        raise SystemExit("pointtrack eval: give --eval-seed or --eval-seeds, not both")
    if args.eval_seed is not None and args.eval_seed < 0:
        raise SystemExit(f"pointtrack eval: --eval-seed must be >= 0, got {args.eval_seed}")
    if args.save_boxes and not args.out:
        raise SystemExit("pointtrack eval: --save-boxes writes into --out DIR: give --out")
    try:
        seeds = check_seeds(
            args.eval_seeds if args.eval_seeds is not None else [args.eval_seed or 0]
        )
        if getattr(args, "weather", None):
            check_weather_arguments(args)
            if len(seeds) > 1 or args.save_boxes:
                raise ValueError("--weather takes one --eval-seed and no --save-boxes")
        device = check_device(args.device)
        batched = device != "cpu"
        num_envs = args.num_envs or (32 if batched else 1)
        one_process = num_envs > 1 or batched
        if args.workers is not None and args.workers > 1 and one_process:
            raise ValueError(
                f"--workers {args.workers} shards tracklets over processes with one env each; "
                "it cannot be combined with --num-envs > 1 or a CUDA device (choose one)"
            )
        workers = resolve_workers(
            args.workers if args.workers is not None or not one_process else 1, "--workers"
        )
        setting = env_kwargs(args)["setting"]  # the env refuses it too; here before --out
        if setting is not None:
            check_setting_layout(setting, "nuscenes" if args.dataset == "nuscenes" else "kitti")
    except ValueError as exc:
        raise SystemExit(f"pointtrack eval: {exc}") from exc
    oracle = None if args.reference == "prediction" else args.reference
    return EvalPlan(
        tuple(seeds), workers, num_envs, device, not batched, oracle, args.network_alone
    )


def check_device(device: str) -> str:
    """``cpu`` or an available ``cuda[:N]`` (``ValueError`` in one line otherwise)."""
    if device == "cpu":
        return device
    if not device.startswith("cuda"):
        raise ValueError(f"--device must be cpu or cuda[:N], got {device!r}")
    from training.pretrain import TrainingError
    from training.pretrain import check_device as check_cuda

    try:
        check_cuda(device)
    except TrainingError as exc:
        raise ValueError(str(exc)) from exc
    return device


def check_out(args: argparse.Namespace) -> None:
    """Refuse an ``--out`` that cannot be created or written, before any evaluation."""
    if args.out:
        from pathlib import Path

        from training.argconfig import save_options
        from training.rundir import remove_stale_temps, unwritable_reason

        out = Path(args.out)
        why = unwritable_reason(out)
        if why is not None:
            raise SystemExit(f"pointtrack eval: cannot write to --out {out}: {why}")
        why = unwritable_reason(out / "boxes") if args.save_boxes else None
        if why is not None:
            raise SystemExit(
                f"pointtrack eval: --save-boxes cannot write to {out / 'boxes'}: {why}"
            )
        remove_stale_temps(out)  # a killed evaluation's half-written report
        save_options(args, out)  # how this evaluation was asked for (loadable by --config)


def load_trackers(args: argparse.Namespace, plan: EvalPlan | None = None) -> dict[str, Any]:
    """``{name: tracker}`` for every ``--tracker``, all loaded (and so validated) up front, on
    ``plan.device`` with ``plan.batch_invariant`` and, with ``plan.network_alone``, the default
    :class:`~trackers.decision.InferenceConfig` (learned trackers; no plan: the CPU, one sample
    per forward, an untrained one seeded by ``args.eval_seed``)."""
    from trackers.decision import InferenceConfig
    from training.loading import load_tracker

    if len(set(args.tracker)) != len(args.tracker):
        raise SystemExit(f"pointtrack eval: a tracker is listed twice: {args.tracker}")
    loaded = {
        name: load_tracker(
            name,
            untrained=getattr(args, "untrained", False),
            seed=plan.seeds[0] if plan else args.eval_seed,
        )
        for name in args.tracker
    }
    for tracker in loaded.values() if plan else ():
        if hasattr(tracker, "batch_invariant") and hasattr(tracker, "to"):
            tracker.to(plan.device)
            tracker.batch_invariant = plan.batch_invariant
        if plan.network_alone and hasattr(tracker, "inference"):
            tracker.inference = InferenceConfig()
    return loaded


def _run_weather(args: argparse.Namespace, plan: EvalPlan, loaded: dict[str, Any]) -> int:
    """``--weather KINDS``: the adverse-weather benchmark (``training.robustness``): each tracker
    clean and under every kind and level, printed as Tables III-IV of Zhao et al. (adverse-weather
    SOT); with ``--out``,
    JSON, table and plots per tracker under ``<out>/weather_<tracker>/``. ``--num-envs N > 1``
    runs every condition on N sub-envs (batched ``act``); ``--workers`` runs the conditions in
    that many processes; ``--fog-mode`` picks the fog rule."""
    from pathlib import Path

    from training.evaluate import env_option_groups, observation_keys_for
    from training.robustness import run_weather_eval

    bases = {}  # tracker name -> the clean env of its option set (one per distinct set)
    for options, names in env_option_groups(loaded, explicit_env_options(args)):
        keys = observation_keys_for([loaded[name] for name in names])
        base = build_env(args, observation_keys=keys, **options)
        bases.update(dict.fromkeys(names, base))
    n = next(iter(bases.values())).num_tracklets
    subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
    for name, tracker in loaded.items():
        base = bases[name]
        slug = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        run_weather_eval(
            tracker,
            base.clone,  # a fresh env per setting, sharing the data
            args.weather,
            levels=args.weather_levels,
            seed=plan.seeds[0],
            weather_seed=args.weather_seed,
            out_dir=Path(args.out) / f"weather_{slug}" if args.out else None,
            analysis=not args.no_analysis,
            progress=not args.no_progress,
            name=name,
            tracklets=subset,
            num_envs=plan.num_envs if plan.num_envs > 1 else None,
            fog_mode=args.fog_mode,
            workers=plan.workers,
            backend=args.backend,
        )
    for base in {id(b): b for b in bases.values()}.values():
        base.close()
    return 0
