"""How often a target leaves the search crop cut around its previous box (docs/table4.md).

For each pair of consecutive frames of a tracklet, the target's new centre, in the previous box's
heading frame, lies outside the env's search crop (half sizes ``scale * l / 2 + offset_m`` and
``scale * w / 2 + offset_m``, the default ``search_enlargement`` (1.25, 2.0)) or not. Printed
per category: the share outside, in the frame the env serves by default (each frame's LiDAR frame:
ego motion included) and, for a nuScenes-layout root, in the reader's ``"scene"`` frame (ego
motion removed: the global frame Open3DSOT's nuScenes loader tracks in, up to one rigid map per
scene; ``--nuscenes-frame scene`` of train / eval / select). Also per category: the share of
pairs whose box centre moves less than ``STILL_M`` ("still": ``previous_box`` holds them).

    python experiments/search_coverage.py --dataset nuscenes --preset default-km --sensor hdl32 \\
        --split train --setting nuscenes-1
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.spec import SEARCH_ENLARGEMENT  # noqa: E402
from training.samples import load_tracklets  # noqa: E402


def outside(
    centres: np.ndarray,
    yaw: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    enlargement: tuple[float, float] = SEARCH_ENLARGEMENT,
) -> np.ndarray:
    """``(T - 1,)`` True where centre ``t + 1`` ``(T, 2)`` lies outside the crop of box ``t``
    enlarged by ``(scale, offset_m)``."""
    scale, offset = enlargement
    d = centres[1:] - centres[:-1]
    c, s = np.cos(-yaw[:-1]), np.sin(-yaw[:-1])
    along, across = c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]
    return (np.abs(along) > scale * length[:-1] / 2 + offset) | (
        np.abs(across) > scale * width[:-1] / 2 + offset
    )


STILL_M = 0.1
"""A pair of frames whose box centre moves less than this (metres, bird's-eye) is "still":
``previous_box`` scores it near IoU 1."""


def _per_category(tracklets, pair_flags) -> dict[str, list[np.ndarray]]:
    """Per category, ``pair_flags(boxes)`` of every tracklet of two frames or more (boxes
    ``(T, 7)`` ``(x, y, z, l, w, h, yaw)``; flags ``(T - 1,)``)."""
    flags = defaultdict(list)
    for tr in tracklets:
        if len(tr.boxes) > 1:
            flags[tr.category].append(pair_flags(tr.boxes))
    return flags


def crop_exits(
    tracklets, enlargement: tuple[float, float] = SEARCH_ENLARGEMENT
) -> dict[str, list[np.ndarray]]:
    """Per category, the outside flags of every tracklet."""
    return _per_category(
        tracklets, lambda b: outside(b[:, :2], b[:, 6], b[:, 3], b[:, 4], enlargement)
    )


def still_pairs(tracklets) -> dict[str, list[np.ndarray]]:
    """Per category, per tracklet: True where the centre moves less than ``STILL_M``."""
    return _per_category(tracklets, lambda b: np.hypot(*np.diff(b[:, :2], axis=0).T) < STILL_M)


def summary(flags: dict[str, list[np.ndarray]]) -> str:
    parts = []
    for name, arrays in sorted(flags.items()):
        f = np.concatenate(arrays)
        parts.append(f"{name} {100 * f.mean():.1f} % of {len(f)}")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", choices=("synthetic", "nuscenes"), default="synthetic")
    parser.add_argument("--preset", default="small-km")
    parser.add_argument("--sensor", default=None)
    parser.add_argument("--world-seed", type=int, default=0)
    parser.add_argument("--split", default="train")
    parser.add_argument("--setting", default="kitti-1")
    parser.add_argument(
        "--with-unseen", action="store_true", help="the setting's unseen categories too"
    )
    parser.add_argument(
        "--enlargement",
        nargs=2,
        type=float,
        action="append",
        metavar=("SCALE", "OFFSET_M"),
        help="a search region to test (repeatable; default the env's 1.25 2)",
    )
    args = parser.parse_args(argv)
    enlargements = [tuple(e) for e in args.enlargement or [SEARCH_ENLARGEMENT]]
    sensor = args.sensor or ("hdl32" if args.dataset == "nuscenes" else "hdl64")
    frames = ("lidar", "scene") if args.dataset == "nuscenes" else ("lidar",)
    for frame in frames:
        tracklets, _, root = load_tracklets(
            args.dataset,
            args.split,
            setting=args.setting,
            preset=args.preset,
            sensor=sensor,
            world_seed=args.world_seed,
            nuscenes_frame=frame,
            trained_only=not args.with_unseen,
        )
        if frame == "lidar":
            which = "all" if args.with_unseen else "observed"
            print(f"{root}, {args.split}, {args.setting} {which}")
        where = {"lidar": "LiDAR frame (the default)", "scene": "scene frame (ego motion removed)"}
        for scale, offset in enlargements:
            exits = summary(crop_exits(tracklets, (scale, offset)))
            print(f"  {where[frame]}, outside the search crop x{scale:g} + {offset:g} m: {exits}")
        print(f"  {where[frame]}, still (< {STILL_M} m): {summary(still_pairs(tracklets))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
