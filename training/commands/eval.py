"""`pointtrack eval`: run trackers step-wise through the environment and report OPE.

Example::

    pointtrack eval --tracker previous_box constant_velocity --dataset synthetic --preset small \\
        --setting kitti-1 --out runs/eval

The env is built by :func:`build_env` from the parsed arguments, so other commands (and the
weather option) can reuse or extend it with extra env keywords.
"""

from __future__ import annotations

import argparse
from typing import Any


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
        "--eval-seed", type=int, default=0,
        help="seed of the point resampling (per tracklet: results do not depend on --num-envs)",
    )
    parser.add_argument("--max-tracklets", type=int, default=None, help="evaluate the first N only")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    # --weather, --weather-levels, --weather-seed, --no-analysis (training.robustness, issue 7)
    from training.robustness import add_weather_arguments

    add_weather_arguments(parser)


def add_env_arguments(parser: argparse.ArgumentParser) -> None:
    """The dataset / env flags shared by `eval` and `demo`."""
    parser.add_argument("--dataset", choices=("synthetic", "kitti"), default="synthetic")
    parser.add_argument(
        "--root",
        default=None,
        metavar="DIR",
        help="KITTI tracking root (label_02/, calib/, velodyne/); --dataset kitti",
    )
    parser.add_argument("--preset", default="small", help="synthetic preset (tiny, small, default)")
    parser.add_argument("--sensor", default="hdl64", help="synthetic sensor (hdl64, hdl32)")
    parser.add_argument("--seed", type=int, default=0, help="synthetic world seed")
    parser.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    parser.add_argument(
        "--setting",
        default=None,
        help="class-agnostic setting (kitti-1, kitti-2, nuscenes-1, nuscenes-2, "
        "class-specific:<Category>); default kitti-1 unless --categories",
    )
    parser.add_argument("--categories", nargs="+", default=None, help="restrict to categories")
    parser.add_argument(
        "--template-mode",
        default="first_and_previous",
        choices=("first_and_previous", "first", "previous", "all"),
    )
    parser.add_argument(
        "--reference", default="prediction", choices=("prediction", "previous_gt", "current_gt")
    )


def env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``TrackingEnv`` / factory keywords from the parsed arguments."""
    setting = args.setting
    if setting is None and not args.categories:
        setting = "kitti-1"
    return {
        "split": args.split,
        "setting": setting,
        "categories": args.categories,
        "template_mode": args.template_mode,
        "reference": args.reference,
    }


def build_env(args: argparse.Namespace, **overrides: Any):
    """The :class:`~envs.tracking_env.TrackingEnv` the arguments describe; ``overrides`` (e.g.
    ``scan_transform=...``) go to the env."""
    from envs.tracking_env import make_kitti_env, make_synthetic_env

    kwargs = env_kwargs(args)
    kwargs.update(overrides)
    if args.dataset == "kitti":
        if not args.root:
            raise SystemExit("pointtrack eval: --dataset kitti needs --root DIR")
        return make_kitti_env(root=args.root, **kwargs)
    if args.root:  # an already generated synthetic world
        return make_kitti_env(root=args.root, **kwargs)
    return make_synthetic_env(preset=args.preset, sensor=args.sensor, seed=args.seed, **kwargs)


def build_vector_env(args: argparse.Namespace, num_envs: int, **overrides: Any):
    """A ``SyncVectorEnv`` of ``num_envs`` copies of :func:`build_env` (the data are shared)."""
    import gymnasium as gym

    env = build_env(args, **overrides)
    return gym.vector.SyncVectorEnv([lambda e=env: e.clone() for _ in range(num_envs)])


def run(args: argparse.Namespace) -> int:
    from training.evaluate import evaluate, format_table, load_tracker, plot_curves, save_report

    if args.num_envs < 1:
        raise SystemExit("pointtrack eval: --num-envs must be >= 1")
    if getattr(args, "weather", None):
        return _run_weather(args)
    env = build_env(args) if args.num_envs == 1 else build_vector_env(args, args.num_envs)
    reports = {}
    for name in args.tracker:
        tracker = load_tracker(name)
        n = env.unwrapped.num_tracklets if args.num_envs == 1 else env.get_attr("num_tracklets")[0]
        subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
        reports[name] = evaluate(
            tracker,
            env,
            seed=args.eval_seed,
            tracklets=subset,
            name=name,
            progress=not args.no_progress,
        )
    print(format_table(reports))
    if args.out:
        from pathlib import Path

        out = Path(args.out)
        save_report(reports, out / "report.json")
        paths = plot_curves(reports, out)
        print(f"wrote {out / 'report.json'} and {', '.join(str(p) for p in paths)}")
    env.close()
    return 0


def _run_weather(args: argparse.Namespace) -> int:
    """``--weather KINDS``: the adverse-weather benchmark (``training.robustness``): each tracker
    clean and under every kind and level, printed as Tables III-IV of ``003_…``; with ``--out``,
    JSON, table and plots per tracker under ``<out>/weather_<tracker>/``. ``--num-envs N > 1``
    runs every condition on N sub-envs (batched ``act``); ``--fog-mode`` picks the fog rule."""
    from pathlib import Path

    from training.evaluate import load_tracker
    from training.robustness import run_weather_eval

    base = build_env(args)
    n = base.num_tracklets
    subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
    for name in args.tracker:
        slug = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        run_weather_eval(
            load_tracker(name),
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
        )
    base.close()
    return 0
