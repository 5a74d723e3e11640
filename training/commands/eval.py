"""`pointtrack eval`: run trackers step-wise through the environment and report OPE.

Example::

    pointtrack eval --tracker previous_box constant_velocity --dataset synthetic --preset small \\
        --setting kitti-1 --out runs/eval

The env is built by :func:`build_env` from the parsed arguments, so other commands (and the
weather option) can reuse or extend it with extra env keywords. Each tracker is evaluated with
the env options it records (``tracker.env_options``, e.g. recipe v2's merged template): one env
per distinct option set; an explicit ``--template-mode`` wins, and ``evaluate`` warns for a
tracker it contradicts (docs/recipe.md).
"""

from __future__ import annotations

import argparse
from typing import Any

from envs.tracking_env import TEMPLATE_MODES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
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
        "--num-envs",
        type=int,
        default=1,
        help="run N sub-envs (SyncVectorEnv) so the tracker acts on batches",
    )
    parser.add_argument(
        "--eval-seed",
        type=int,
        default=0,
        help="seed of the point resampling (per tracklet: results do not depend on --num-envs)",
    )
    parser.add_argument(
        "--max-tracklets",
        type=int,
        default=None,
        metavar="N",
        help="evaluate the first N only (N >= 1)",
    )
    parser.add_argument(
        "--untrained",
        action="store_true",
        help="allow a learned tracker's bare name (p2b, bat, gpt): a randomly initialised "
        "model seeded by --eval-seed (without this flag such a name is refused)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    # --weather, --weather-levels, --weather-seed, --no-analysis (training.robustness, issue 7)
    from training.robustness import add_weather_arguments

    add_weather_arguments(parser)


def add_env_arguments(parser: argparse.ArgumentParser) -> None:
    """The dataset / env flags shared by `eval` and `demo`."""
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
    parser.add_argument("--preset", default="small", help="synthetic preset (tiny, small, default)")
    parser.add_argument("--sensor", default="hdl64", help="synthetic sensor (hdl64, hdl32)")
    parser.add_argument("--seed", type=int, default=0, help="synthetic world seed")
    parser.add_argument(
        "--split",
        default="test",
        choices=("train", "val", "test", "all"),
        help="scenes: train 0-16, val 17-18, test 19-20 (KITTI's split)",
    )
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
    from envs.tracking_env import make_kitti_env, make_synthetic_env

    kwargs = env_kwargs(args)
    kwargs.update(overrides)
    if args.dataset == "nuscenes":
        from envs.data.nuscenes import SOT_SPLITS
        from envs.nuscenes_env import make_nuscenes_env

        kwargs["split"] = SOT_SPLITS[kwargs["split"]]
        if args.root:
            return make_nuscenes_env(root=args.root, version=args.version, **kwargs)
        return make_nuscenes_env(
            version=args.version, preset=args.preset, sensor=args.sensor, seed=args.seed, **kwargs
        )
    if args.dataset == "kitti" and not args.root:
        raise SystemExit("pointtrack eval: --dataset kitti needs --root DIR")
    if not args.root:
        return make_synthetic_env(preset=args.preset, sensor=args.sensor, seed=args.seed, **kwargs)
    if not getattr(args, "allow_missing_scenes", False):
        return make_kitti_env(root=args.root, **kwargs)  # KITTI, or a generated world
    from envs.data import KittiTracking, get_setting
    from envs.tracking_env import TrackingEnv

    categories = kwargs.pop("categories")
    load = categories or (get_setting(kwargs["setting"]).categories if kwargs["setting"] else None)
    dataset = KittiTracking(args.root, kwargs["split"], load, allow_missing_scenes=True)
    return TrackingEnv(dataset, categories=categories, **kwargs)


def build_vector_env(args: argparse.Namespace, num_envs: int, **overrides: Any):
    """A ``SyncVectorEnv`` of ``num_envs`` copies of :func:`build_env` (the data are shared)."""
    import gymnasium as gym

    env = build_env(args, **overrides)
    return gym.vector.SyncVectorEnv([lambda e=env: e.clone() for _ in range(num_envs)])


def run(args: argparse.Namespace) -> int:
    from training.evaluate import (
        env_option_groups,
        evaluate,
        format_table,
        observation_keys_for,
        plot_curves,
        save_report,
    )

    check_args(args)
    if getattr(args, "weather", None):
        return _run_weather(args)
    # every tracker before any data or evaluation, so a typo in the last one fails in a second
    loaded = load_trackers(args)
    check_out(args)
    reports = {}
    # one env per distinct option set the trackers record (e.g. recipe v2's template mode)
    for options, names in env_option_groups(loaded, explicit_env_options(args)):
        group = [loaded[name] for name in names]
        keys = observation_keys_for(group)  # e.g. M2-Track's previous frame
        env = (
            build_env(args, observation_keys=keys, **options)
            if args.num_envs == 1
            else build_vector_env(args, args.num_envs, observation_keys=keys, **options)
        )
        n = env.unwrapped.num_tracklets if args.num_envs == 1 else env.get_attr("num_tracklets")[0]
        subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
        for name, tracker in zip(names, group, strict=True):
            reports[name] = evaluate(
                tracker,
                env,
                seed=args.eval_seed,
                tracklets=subset,
                name=name,
                progress=not args.no_progress,
            )
        env.close()
    reports = {name: reports[name] for name in loaded}  # the order of --tracker
    print(format_table(reports))
    if args.out:
        from pathlib import Path

        out = Path(args.out)
        save_report(reports, out / "report.json")
        paths = plot_curves(reports, out)
        print(f"wrote {out / 'report.json'} and {', '.join(str(p) for p in paths)}")
    return 0


def check_args(args: argparse.Namespace) -> None:
    """Refuse bad counts before anything is built (``SystemExit`` with one line; the CLI turns
    it into exit status 2)."""
    if args.num_envs < 1:
        raise SystemExit(f"pointtrack eval: --num-envs must be >= 1, got {args.num_envs}")
    if args.max_tracklets is not None and args.max_tracklets < 1:
        raise SystemExit(
            f"pointtrack eval: --max-tracklets must be >= 1, got "
            f"{args.max_tracklets} (leave it out to evaluate every tracklet)"
        )


def check_out(args: argparse.Namespace) -> None:
    """Refuse an ``--out`` that cannot be created or written, before any evaluation."""
    if args.out:
        from pathlib import Path

        from training.checkpoint import remove_stale_temps, unwritable_reason

        out = Path(args.out)
        why = unwritable_reason(out)
        if why is not None:
            raise SystemExit(f"pointtrack eval: cannot write to --out {out}: {why}")
        remove_stale_temps(out)  # a killed evaluation's half-written report


def load_trackers(args: argparse.Namespace) -> dict[str, Any]:
    """``{name: tracker}`` for every ``--tracker``, all loaded (and so validated) up front."""
    from training.evaluate import load_tracker

    if len(set(args.tracker)) != len(args.tracker):
        raise SystemExit(f"pointtrack eval: a tracker is listed twice: {args.tracker}")
    return {
        name: load_tracker(name, untrained=args.untrained, seed=args.eval_seed)
        for name in args.tracker
    }


def _run_weather(args: argparse.Namespace) -> int:
    """``--weather KINDS``: the adverse-weather benchmark (``training.robustness``): each tracker
    clean and under every kind and level, printed as Tables III-IV of Zhao et al. (adverse-weather
    SOT); with ``--out``,
    JSON, table and plots per tracker under ``<out>/weather_<tracker>/``. ``--num-envs N > 1``
    runs every condition on N sub-envs (batched ``act``); ``--fog-mode`` picks the fog rule."""
    from pathlib import Path

    from training.evaluate import env_option_groups, observation_keys_for
    from training.robustness import run_weather_eval

    loaded = load_trackers(args)
    check_out(args)
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
            seed=args.eval_seed,
            weather_seed=args.weather_seed,
            out_dir=Path(args.out) / f"weather_{slug}" if args.out else None,
            analysis=not args.no_analysis,
            progress=not args.no_progress,
            name=name,
            tracklets=subset,
            num_envs=args.num_envs if args.num_envs > 1 else None,
            fog_mode=args.fog_mode,
            workers=args.workers,
            backend=args.backend,
        )
    for base in {id(b): b for b in bases.values()}.values():
        base.close()
    return 0
