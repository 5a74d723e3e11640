"""How often a target leaves the search crop cut around its previous box (docs/table4.md).

For each pair of consecutive frames of a tracklet, the target's new centre, in the previous box's
heading frame, lies outside the env's search crop (half sizes ``scale * l / 2 + offset_m`` and
``scale * w / 2 + offset_m``, the default ``search_enlargement`` (1.25, 2.0)) or not. Printed
per category: the share outside, in the frame the env serves (each frame's LiDAR frame: ego
motion included) and, for a nuScenes-layout root, in the global frame of the annotation table
(ego motion removed, as Open3DSOT's nuScenes loader does).

    python experiments/search_coverage.py --dataset nuscenes --preset default-km --sensor hdl32 \\
        --split train --setting nuscenes-1
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.spec import SEARCH_ENLARGEMENT  # noqa: E402
from training.samples import load_tracklets  # noqa: E402


def outside(
    centres: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """``(T - 1,)`` True where centre ``t + 1`` ``(T, 2)`` lies outside the crop of box ``t``."""
    scale, offset = SEARCH_ENLARGEMENT
    d = centres[1:] - centres[:-1]
    c, s = np.cos(-yaw[:-1]), np.sin(-yaw[:-1])
    along, across = c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]
    return (np.abs(along) > scale * length[:-1] / 2 + offset) | (
        np.abs(across) > scale * width[:-1] / 2 + offset
    )


def lidar_frame_shares(tracklets) -> dict[str, list[np.ndarray]]:
    """Per category, the outside flags of every tracklet, boxes ``(x, y, z, l, w, h, yaw)``."""
    flags = defaultdict(list)
    for tr in tracklets:
        b = tr.boxes
        if len(b) > 1:
            flags[tr.category].append(outside(b[:, :2], b[:, 6], b[:, 3], b[:, 4]))
    return flags


def global_frame_shares(
    table_dir: Path, annotation_tokens: list[tuple[str, ...]], categories: list[str]
) -> dict[str, list[np.ndarray]]:
    """The same from the global boxes of a nuScenes ``sample_annotation`` table (size ``(w, l,
    h)``, rotation ``(w, x, y, z)``): per tracklet its frames' annotation tokens and category."""
    rows = json.loads((table_dir / "sample_annotation.json").read_text())
    annotations = {a["token"]: a for a in rows}
    flags = defaultdict(list)
    for tokens, category in zip(annotation_tokens, categories, strict=True):
        chain = [annotations[t] for t in tokens]
        if len(chain) < 2:
            continue
        q = np.array([a["rotation"] for a in chain])
        yaw = np.arctan2(
            2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2] ** 2 + q[:, 3] ** 2)
        )
        size = np.array([a["size"] for a in chain])
        centres = np.array([a["translation"][:2] for a in chain])
        flags[category].append(outside(centres, yaw, size[:, 1], size[:, 0]))
    return flags


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
    args = parser.parse_args(argv)
    sensor = args.sensor or ("hdl32" if args.dataset == "nuscenes" else "hdl64")
    if args.dataset == "nuscenes":
        from envs.data.nuscenes import SOT_SPLITS, NuScenesTracking
        from envs.data.settings import get_setting
        from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, ensure_nuscenes_world

        root = ensure_nuscenes_world(args.preset, sensor, args.world_seed, DEFAULT_VERSION)
        categories = list(get_setting(args.setting).observed)
        data = NuScenesTracking(root, DEFAULT_VERSION, SOT_SPLITS[args.split], categories)
        tracklets = data.tracklets
    else:
        tracklets, _, root = load_tracklets(
            "synthetic",
            args.split,
            setting=args.setting,
            preset=args.preset,
            sensor=sensor,
            world_seed=args.world_seed,
        )
    print(f"{root}, {args.split}, {args.setting} observed: outside the previous box's search crop")
    print(f"  LiDAR frame (what the env serves): {summary(lidar_frame_shares(tracklets))}")
    if args.dataset == "nuscenes":
        flags = global_frame_shares(
            Path(root) / DEFAULT_VERSION,
            data.annotation_tokens,
            [tr.category for tr in tracklets],
        )
        print(f"  global frame (ego motion removed): {summary(flags)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
