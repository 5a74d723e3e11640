"""`pointtrack generate`: write a synthetic LiDAR world in the KITTI tracking layout, or with
``--layout nuscenes`` in the nuScenes v1.0 layout (``envs.synthetic.nuscenes_layout``)."""

from __future__ import annotations

import argparse
import sys
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags (valid values come from the synthetic module's tables)."""
    parser.add_argument(
        "--out", help="output directory (created atomically); required unless --verify or --cache"
    )
    parser.add_argument(
        "--cache",
        action="store_true",
        help="generate into the world cache instead of --out, where the envs and every "
        "command's --preset find it (e.g. before parallel jobs that would each build it); an "
        "intact cached world is reused; prints its path",
    )
    parser.add_argument(
        "--verify",
        metavar="DIR",
        default=None,
        help="check the world in DIR against its manifest (every file's size and SHA-256) "
        "and exit: 0 intact, 1 damaged (one line per problem)",
    )
    parser.add_argument(
        "--preset",
        default="small",
        help="world size: tiny (seconds, tests), small (about a minute, demo), default "
        "(21 scenes split like KITTI)",
    )
    parser.add_argument(
        "--sensor",
        default=None,
        help="hdl64 (KITTI-like, 64 beams) or hdl32 (nuScenes-like); default per layout",
    )
    parser.add_argument(
        "--layout",
        choices=("kitti", "nuscenes"),
        default="kitti",
        help="kitti (label_02/, calib/, velodyne/) or nuscenes (VERSION/*.json, samples/LIDAR_TOP; "
        "2 Hz key frames, default sensor hdl32)",
    )
    parser.add_argument(
        "--version", default=None, help="--layout nuscenes: table folder (default v1.0-mini)"
    )
    parser.add_argument("--seed", type=int, default=0, help="non-negative integer seed")
    parser.add_argument(
        "--from-labels",
        default=None,
        metavar="DIR",
        help="replay the objects of a KITTI label_02 + calib folder (real categories, sizes, "
        "trajectories) and write exactly its labels",
    )
    parser.add_argument(
        "--scan-frames",
        type=int,
        default=None,
        metavar="N",
        help="with --from-labels: simulate scans only for the first N frames of each scene",
    )
    parser.add_argument(
        "--scenes",
        default=None,
        help="with --from-labels: comma-separated scene numbers to replay (default: all)",
    )
    parser.add_argument(
        "--preview", action="store_true", help="also write OUT/preview.png (bird's-eye + 3D)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a different world")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args: argparse.Namespace) -> int:
    from envs.synthetic import generate_world, verify_world
    from envs.synthetic.preview import save_preview

    if args.verify:
        problems = verify_world(args.verify, digests=True)
        for line in problems:
            print(f"pointtrack generate --verify: {line}", file=sys.stderr)
        if not problems:
            print(f"{args.verify}: every file matches the manifest (sizes and SHA-256)")
        return 1 if problems else 0
    if args.cache:
        return _run_cache(args)
    if not args.out:
        raise SystemExit("pointtrack generate: --out DIR is required (or --verify DIR, --cache)")

    scenes = None
    if args.scenes:
        try:
            scenes = tuple(int(s) for s in args.scenes.split(","))
        except ValueError:
            print(
                f"pointtrack generate: --scenes must be integers, got {args.scenes!r}",
                file=sys.stderr,
            )
            return 2
    start = time.perf_counter()
    if args.layout == "nuscenes":
        return _run_nuscenes(args, start)
    if args.version is not None:
        print("pointtrack generate: --version applies to --layout nuscenes", file=sys.stderr)
        return 2
    try:
        root = generate_world(
            args.out,
            args.preset,
            args.sensor or "hdl64",
            args.seed,
            args.from_labels,
            progress=False if args.no_progress else True,
            overwrite=args.overwrite,
            scan_frames=args.scan_frames,
            scenes=scenes,
        )
    except (ValueError, OSError) as exc:
        print(f"pointtrack generate: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - start
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    print(f"world written to {root} in {elapsed:.1f} s ({size / 1e6:.1f} MB)")
    if args.preview:
        png = save_preview(root, root / "preview.png")
        print(f"preview: {png}")
    return 0


def _run_nuscenes(args: argparse.Namespace, start: float) -> int:
    from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, generate_nuscenes_world

    if args.from_labels or args.scan_frames is not None or args.scenes:
        print(
            "pointtrack generate: --from-labels, --scan-frames and --scenes apply to "
            "--layout kitti",
            file=sys.stderr,
        )
        return 2
    try:
        root = generate_nuscenes_world(
            args.out,
            args.preset,
            args.sensor or "hdl32",
            args.seed,
            args.version or DEFAULT_VERSION,
            progress=False if args.no_progress else True,
            overwrite=args.overwrite,
        )
    except (ValueError, FileExistsError) as exc:
        print(f"pointtrack generate: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - start
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    print(f"nuScenes-layout world written to {root} in {elapsed:.1f} s ({size / 1e6:.1f} MB)")
    if args.preview:
        print(
            "pointtrack generate: --preview draws KITTI-layout worlds only; skipped",
            file=sys.stderr,
        )
    return 0


def _run_cache(args: argparse.Namespace) -> int:
    """``--cache``: the world through ``ensure_world`` / ``ensure_nuscenes_world``, the same
    entry the envs use, so its cache path and identity are theirs."""
    from envs.synthetic import ensure_world
    from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, ensure_nuscenes_world

    clashing = [
        flag
        for flag, given in (
            ("--out", args.out),
            ("--overwrite", args.overwrite),
            ("--preview", args.preview),
            ("--scan-frames", args.scan_frames is not None),
            ("--scenes", args.scenes),
        )
        if given
    ]
    if args.layout == "nuscenes" and args.from_labels:
        clashing.append("--from-labels")
    if args.layout == "kitti" and args.version is not None:
        clashing.append("--version")
    if clashing:
        print(
            f"pointtrack generate: --cache does not take {', '.join(clashing)} "
            f"(a cached world is identified by layout, preset, sensor, seed"
            f"{' and version' if args.layout == 'nuscenes' else ' and --from-labels'})",
            file=sys.stderr,
        )
        return 2
    progress = False if args.no_progress else None
    try:
        if args.layout == "nuscenes":
            root = ensure_nuscenes_world(
                args.preset,
                args.sensor or "hdl32",
                args.seed,
                args.version or DEFAULT_VERSION,
                progress=progress,
            )
        else:
            root = ensure_world(
                args.preset, args.sensor or "hdl64", args.seed, args.from_labels, progress=progress
            )
    except (ValueError, OSError) as exc:
        print(f"pointtrack generate: {exc}", file=sys.stderr)
        return 2
    print(root)
    return 0
