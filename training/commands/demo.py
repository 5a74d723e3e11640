"""`pointtrack demo`: generate the small synthetic world (once) and compare the trackers on the
observed and unseen categories of a class-agnostic setting (default ``kitti-1``).

Trackers: the two baselines plus every shipped checkpoint that ``trackers.load`` can load
(``p2b-kitti1-u``, ``p2b-kitti1-w``, ``bat-…``, ``gpt-…``); missing ones are skipped with a note.
Learned trackers' tracklets are sharded over ``--workers`` processes (every usable core).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

# constant_velocity alone never moves (zero motion at the first step), so the demo shows its
# variant that estimates the first motion from the points (see trackers.baselines)
BASELINE_NAMES = ("previous_box", "constant_velocity:points")
CHECKPOINT_NAMES = tuple(
    f"{model}-{setting}-{kind}"
    for model in ("p2b", "bat", "gpt")
    for setting in ("kitti1", "kitti2")
    for kind in ("u", "w", "s")
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    from training.commands.eval import add_world_arguments

    add_world_arguments(parser, "which scenes are evaluated")
    parser.add_argument(
        "--setting",
        default="kitti-1",
        help="class-agnostic setting: observed and unseen categories",
    )
    parser.add_argument(
        "--tracker",
        nargs="+",
        default=None,
        help="trackers to compare (default: baselines + shipped checkpoints)",
    )
    parser.add_argument(
        "--out",
        default="runs/demo",
        metavar="DIR",
        help="where the JSON report and the plots go (runs/ is ignored by git)",
    )
    parser.add_argument(
        "--num-envs",
        type=int,
        default=1,
        help="batch size for learned trackers (sub-envs of a SyncVectorEnv; then --workers is 1)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="processes the learned trackers' tracklets are sharded over, one torch thread each "
        "(default: every usable core; the results do not depend on it)",
    )
    parser.add_argument(
        "--max-tracklets",
        type=int,
        default=None,
        metavar="N",
        help="evaluate the first N tracklets only (N >= 1)",
    )
    parser.add_argument(
        "--max-frames",
        type=int,
        default=400,
        help="when learned trackers run, evaluate every tracker on the same category-balanced "
        "subset of about this many frames (0: all frames)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _shipped_checkpoints(setting: str) -> list[str]:
    """Shipped checkpoint names for the setting (``kitti-1`` -> ``*-kitti1-*``), in the order
    p2b, bat, gpt then anything else found."""
    tag = setting.replace("-", "")
    try:
        import trackers

        found = {n for n in trackers.available() if "-" in n}
    except Exception:  # noqa: BLE001 - a broken trackers package must not break the demo
        found = set()
    names = [n for n in CHECKPOINT_NAMES if f"-{tag}-" in n and n in found]
    return names + sorted(n for n in found if f"-{tag}-" in n and n not in names)


# What generating a world costs the first time (seconds on a 2-core CPU, MB on disk; measured
# with `pointtrack generate`); the world is written once into the cache and reused afterwards.
WORLD_COST = {"tiny": (10, 70), "small": (60, 670), "default": (60, 3800)}


def announcement(preset: str, sensor: str, seed: int) -> str:
    """What the demo will cost and where it writes, printed before anything starts."""
    from envs.synthetic import default_cache_dir, get_preset

    get_preset(preset)  # a bad name fails here, listing the valid ones
    gen_s, mb = WORLD_COST.get(preset, WORLD_COST["default"])
    return (
        f"[demo] world preset={preset} sensor={sensor} seed={seed}: the first time it is "
        f"generated (about {gen_s} s, {mb} MB) into the cache {default_cache_dir() / 'worlds'} "
        "(set POINTTRACK_CACHE to move it) and reused afterwards; then each tracker is evaluated "
        "(seconds for the baselines, a few minutes for the learned trackers on a 2-core CPU)"
    )


def balanced_subset(categories: list[str], lengths: list[int], max_frames: int) -> list[int]:
    """Tracklet indices taken round-robin over the categories (in order of first appearance)
    until about ``max_frames`` frames are covered; sorted."""
    by_cat: dict[str, list[int]] = {}
    for i, c in enumerate(categories):
        by_cat.setdefault(c, []).append(i)
    chosen: list[int] = []
    frames = 0
    queues = [list(v) for v in by_cat.values()]
    while frames < max_frames and any(queues):
        for q in queues:
            if q and frames < max_frames:
                i = q.pop(0)
                chosen.append(i)
                frames += lengths[i]
    return sorted(chosen)


def run(args: argparse.Namespace) -> int:
    from envs.plotting import pyplot
    from envs.synthetic import ensure_world
    from envs.tracking_env import OBSERVATION_KEYS, make_kitti_env
    from trackers.baselines import BASELINES
    from training.evaluate import (
        env_options_for,
        evaluate,
        format_table,
        observation_keys_for,
        plot_curves,
        save_report,
    )
    from training.loading import load_tracker
    from training.parallel import resolve_workers

    if args.max_tracklets is not None and args.max_tracklets < 1:
        raise SystemExit(f"--max-tracklets must be >= 1, got {args.max_tracklets}")
    if args.num_envs < 1:
        raise SystemExit(f"--num-envs must be >= 1, got {args.num_envs}")
    if args.num_envs > 1 and args.workers not in (None, 1):
        raise SystemExit("--workers > 1 cannot be combined with --num-envs > 1 (choose one)")
    workers = resolve_workers(1 if args.num_envs > 1 else args.workers, "--workers")
    start = time.perf_counter()
    print(announcement(args.preset, args.sensor, args.seed), flush=True)
    root = ensure_world(preset=args.preset, sensor=args.sensor, seed=args.seed)
    env = make_kitti_env(root=str(root), split=args.split, setting=args.setting)
    n = env.num_tracklets
    subset = None if args.max_tracklets is None else list(range(min(args.max_tracklets, n)))
    print(
        f"[demo] {root}: split {args.split}, setting {args.setting}: {n} tracklets, "
        f"{sum(env.tracklet_lengths)} frames",
        flush=True,
    )
    names = (
        list(args.tracker)
        if args.tracker
        else list(BASELINE_NAMES) + _shipped_checkpoints(args.setting)
    )
    learned = [n for n in names if n not in BASELINE_NAMES and n not in BASELINES]
    total = sum(env.tracklet_lengths)
    if subset is None and learned and args.max_frames and total > args.max_frames:
        cats = [t.category for t in env.tracklets]
        subset = balanced_subset(cats, env.tracklet_lengths, args.max_frames)
        print(
            f"[demo] learned trackers are slow on CPU: every tracker runs on the same "
            f"{len(subset)} tracklets ({sum(env.tracklet_lengths[i] for i in subset)} frames, "
            "balanced over categories; --max-frames 0 for all)",
            flush=True,
        )
    reports = {}
    for name in names:
        try:
            if name == "constant_velocity:points":
                tracker = BASELINES["constant_velocity"](init="points")
            elif name in BASELINES:
                tracker = BASELINES[name]()
            else:
                tracker = load_tracker(name)
        except Exception as exc:  # noqa: BLE001 - skip what cannot be loaded, say why
            print(f"[demo] skipping {name}: {type(exc).__name__}: {exc}", flush=True)
            continue
        options = env_options_for([tracker])
        keys = observation_keys_for([tracker])
        # a tracker trained with other env options (recipe v2) or reading an opt-in
        # observation key (M2-Track's previous frame) gets its own env
        own = options or keys != OBSERVATION_KEYS
        target = env
        if own:
            target = make_kitti_env(
                root=str(root),
                split=args.split,
                setting=args.setting,
                observation_keys=keys,
                **options,
            )
        baseline = name in BASELINES or name in BASELINE_NAMES  # microseconds per act
        reports[name] = evaluate(
            tracker,
            target,
            tracklets=subset,
            name=name,
            progress=not args.no_progress,
            num_envs=1 if baseline else args.num_envs,
            workers=1 if baseline else workers,
            warm_up=pyplot,  # for the plots, beside the workers (imported once per process)
        )
        if own:
            target.close()
    if not reports:
        print("[demo] no tracker could be loaded")
        return 1
    print()
    print(format_table(reports))
    out = Path(args.out)
    save_report(reports, out / "report.json")
    paths = plot_curves(reports, out, workers=workers)
    print(
        f"\n[demo] wrote {out / 'report.json'}, {', '.join(str(p) for p in paths)} "
        f"in {time.perf_counter() - start:.0f} s"
    )
    return 0
