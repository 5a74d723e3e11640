"""How far apart KITTI's boxes are in the two box conventions (docs/recipe.md).

For every labelled box of a split: the centre distance and yaw difference between
``box_convention="lidar"`` and ``"open3dsot"``, and the OPE Success / Precision a tracker that
is perfect in one convention scores in the other (every frame after each tracklet's first).

    PYTHONPATH=$PWD python experiments/kitti_box_conventions.py ../shared/kitti-tracking-labels
"""

from __future__ import annotations

import argparse

import numpy as np

from envs.data import KittiTracking
from envs.geometry import center_distance, iou_3d, wrap_yaw
from envs.metrics import precision_auc, success_auc


def compare(root: str, split: str, categories: list[str]) -> dict[str, float]:
    lidar = KittiTracking(root, split, categories)
    o3d = KittiTracking(root, split, categories, box_convention="open3dsot")
    a = np.concatenate([np.asarray(tr.boxes)[1:] for tr in lidar.tracklets])
    b = np.concatenate([np.asarray(tr.boxes)[1:] for tr in o3d.tracklets])
    dist = center_distance(a, b)
    dyaw = np.abs(wrap_yaw(a[:, 6] - b[:, 6]))
    return {
        "boxes": len(a),
        "centre_median_m": float(np.median(dist)),
        "centre_max_m": float(dist.max()),
        "yaw_median_deg": float(np.degrees(np.median(dyaw))),
        "success": success_auc(iou_3d(a, b)),
        "precision": precision_auc(dist),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", help="KITTI tracking root (label_02/, calib/)")
    parser.add_argument("--split", default="test")
    args = parser.parse_args()
    print(f"split {args.split}: lidar vs open3dsot boxes (frames after each tracklet's first)")
    print("category    boxes  centre median / max (m)  yaw median (deg)  Success  Precision")
    four = ["Car", "Pedestrian", "Van", "Cyclist"]
    for category, categories in [*((c, [c]) for c in four), ("all four", four)]:
        r = compare(args.root, args.split, categories)
        centre = f"{r['centre_median_m']:.3f} / {r['centre_max_m']:.3f}"
        print(
            f"{category:10s} {r['boxes']:6d}  {centre:25s}  {r['yaw_median_deg']:16.2f}  "
            f"{r['success']:7.1f}  {r['precision']:9.1f}"
        )


if __name__ == "__main__":
    main()
