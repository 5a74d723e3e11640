"""`pointtrack render`: watch trackers on one tracklet — a video or a rerun 3D recording.

Examples::

    pointtrack render --tracker p2b-kitti1-u previous_box --tracklet 0019/3 --preset tiny \\
        --out runs/render/0019_3.mp4
    pointtrack render --tracker p2b-kitti1-u --tracklet 0019/3 --preset tiny \\
        --weather fog:3 --viewer rerun --out runs/render/0019_3.rrd   # then: rerun that.rrd

A video (``.mp4`` or ``.gif``, the ``video`` extra) shows the env's bird's-eye view of each
tracker's search region side by side (points grey, reference box blue, ground truth green,
prediction red) with the frame and the IoU, one video frame per tracked frame. ``--viewer
rerun`` (``.rrd``, the ``viewer`` extra) logs the scans, the crops, the boxes and the per-frame
IoU in 3D (:mod:`training.rerun_view`). The observations are those ``pointtrack eval`` scores
with the same ``--eval-seed``.
"""

from __future__ import annotations

import argparse
from typing import Any

VIEWERS = {"video": (".mp4", ".gif"), "rerun": (".rrd",)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    from training.commands.eval import add_env_arguments

    parser.add_argument(
        "--tracker",
        nargs="+",
        required=True,
        metavar="NAME_OR_PATH",
        help="tracker name(s) or checkpoint path(s); several are shown side by side",
    )
    parser.add_argument(
        "--tracklet", required=True, metavar="ID", help="the tracklet id, e.g. 0019/3"
    )
    parser.add_argument(
        "--out", required=True, metavar="FILE", help="x.mp4 or x.gif (video), x.rrd (rerun)"
    )
    parser.add_argument(
        "--viewer",
        choices=tuple(VIEWERS),
        default="video",
        help="video: the bird's-eye view as MP4/GIF; rerun: a 3D recording",
    )
    add_env_arguments(parser)
    parser.add_argument("--eval-seed", type=int, default=0, help="seed of the point resampling")
    parser.add_argument(
        "--max-frames", type=int, default=None, metavar="N", help="show the first N tracked frames"
    )
    parser.add_argument("--fps", type=float, default=10.0, help="video frames per second")
    parser.add_argument(
        "--weather",
        default=None,
        metavar="KIND:LEVEL",
        help="run under this weather (fog, rain or snow; level 1..5), e.g. fog:3",
    )
    parser.add_argument(
        "--weather-seed", type=int, default=0, help="seed of the weather corruption"
    )
    parser.add_argument(
        "--untrained",
        action="store_true",
        help="allow a learned tracker's bare name (a random initialisation seeded by --eval-seed)",
    )


def check_args(args: argparse.Namespace) -> None:
    """Refuse a bad ``--out`` / count / weather before anything is built (one line)."""
    from pathlib import Path

    from training.rundir import unwritable_reason

    suffixes = VIEWERS[args.viewer]
    out = Path(args.out)
    if out.suffix.lower() not in suffixes:
        raise SystemExit(f"--viewer {args.viewer} writes {' or '.join(suffixes)}, not --out {out}")
    why = unwritable_reason(out.parent)
    if why is not None:
        raise SystemExit(f"cannot write --out {out}: {why}")
    if args.max_frames is not None and args.max_frames < 1:
        raise SystemExit(f"--max-frames must be >= 1, got {args.max_frames}")
    if not args.fps > 0:
        raise SystemExit(f"--fps must be > 0, got {args.fps}")


def weather_transform(spec: str | None, seed: int) -> Any:
    """``KIND:LEVEL`` -> an ``envs.weather.WeatherTransform`` (``None`` for no weather)."""
    if spec is None:
        return None
    from envs.weather import WeatherTransform

    kind, sep, level = spec.partition(":")
    if not sep or not level.strip().isdigit():
        raise SystemExit(f"--weather {spec!r}: expected KIND:LEVEL, e.g. fog:3")
    return WeatherTransform(kind.strip(), int(level), seed=seed)


def run(args: argparse.Namespace) -> int:
    from training.commands.eval import build_env, explicit_env_options, load_trackers
    from training.evaluate import env_option_groups, observation_keys_for
    from training.extras import require
    from training.video import check_tracklet, compose_frames, run_episode, write_video

    check_args(args)
    if len(set(args.tracker)) != len(args.tracker):
        raise SystemExit(f"a tracker is listed twice: {args.tracker}")
    if args.viewer == "video":
        require("imageio", "video", "pointtrack render (video)")
    else:
        require("rerun", "viewer", "pointtrack render --viewer rerun")
    transform = weather_transform(args.weather, args.weather_seed)
    loaded = load_trackers(args)  # every name checked before any data is built
    traces = {}
    tracklet = None
    for options, names in env_option_groups(loaded, explicit_env_options(args)):
        keys = observation_keys_for([loaded[n] for n in names])
        env = build_env(
            args,
            observation_keys=keys,
            render_mode="rgb_array",
            scan_transform=transform,
            **options,
        )
        tracklet = env.unwrapped.tracklets[check_tracklet(env, args.tracklet)]
        for name in names:
            traces[name] = run_episode(
                loaded[name],
                env,
                args.tracklet,
                name=name,
                seed=args.eval_seed,
                max_steps=args.max_frames,
            )
        env.close()
    ordered = [traces[name] for name in loaded]  # the order of --tracker
    for trace in ordered:
        mean = sum(trace.ious) / len(trace.ious)
        print(
            f"{trace.tracker}: tracklet {trace.tracklet}, {len(trace)} frames, mean IoU {mean:.3f}"
        )
    if args.viewer == "video":
        path = write_video(compose_frames(ordered), args.out, fps=args.fps)
    else:
        from training.rerun_view import write_recording

        path = write_recording(ordered, tracklet, args.out, scan_transform=transform)
    print(f"wrote {path}")
    return 0
