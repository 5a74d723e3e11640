"""Success / Precision of ``pointtrack eval`` reports by how fast the target moves: each
tracklet's mean ground-truth displacement per frame (xy, m, in the frame its boxes are labelled
in: the sensor's), binned, with the frame-weighted mean of its per-tracklet scores (equal to
the pooled OPE score of the bin's frames: Success and Precision are means over frames). ::

    pointtrack eval --tracker previous_box bat-kitti1-u --dataset synthetic --preset default \\
        --seed 1 --split train --setting kitti-1 --categories Van --out runs/van-w1
    python experiments/motion_breakdown.py runs/van-w1/report.json --preset default \\
        --world-seed 1 --split train --setting kitti-1

A target that does not move (a parked car seen from a standing sensor) is where
``previous_box`` is perfect; the static bin shows how much a learned tracker gives away there.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

BIN_EDGES_M = (0.0, 0.05, 0.5, 1.5)
"""Lower edges of the speed bins (m per frame): static, slow, moving, fast."""


def mean_step_m(boxes: np.ndarray) -> float:
    """Mean xy distance (m) between consecutive boxes ``(T, 7)``; 0 for one box."""
    boxes = np.asarray(boxes, dtype=np.float64)
    if len(boxes) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(boxes[:, :2], axis=0), axis=1).mean())


def speed_bin(step_m: float, edges: Sequence[float] = BIN_EDGES_M) -> str:
    """The label of the bin ``[edge_i, edge_i+1)`` holding ``step_m``."""
    i = int(np.searchsorted(edges, step_m, side="right")) - 1
    upper = f"{edges[i + 1]:g}" if i + 1 < len(edges) else "inf"
    return f"[{edges[i]:g}, {upper})"


def breakdown(
    report: Mapping,
    steps_m: Mapping[str, float],
    edges: Sequence[float] = BIN_EDGES_M,
    category: str | None = None,
) -> dict[str, dict[str, float]]:
    """``bin -> {"tracklets", "frames", "success", "precision"}`` over one tracker's report
    (its tracklets of ``category`` only, when given).

    ``steps_m`` maps a tracklet id to its :func:`mean_step_m`; a reported tracklet missing
    from it is an error naming it (the report was made on other data)."""
    groups: dict[str, list[Mapping]] = {}
    for row in report["per_tracklet"]:
        if category is not None and row["category"] != category:
            continue
        if row["tracklet"] not in steps_m:
            raise KeyError(
                f"tracklet {row['tracklet']!r} of the report is not in the data given "
                f"(another world, split or preset?)"
            )
        groups.setdefault(speed_bin(steps_m[row["tracklet"]], edges), []).append(row)
    result = {}
    for label in [speed_bin(e, edges) for e in edges]:
        rows = groups.get(label, [])
        frames = np.array([r["frames"] for r in rows], dtype=np.float64)
        entry = {"tracklets": len(rows), "frames": int(frames.sum())}
        for key in ("success", "precision"):
            values = np.array([r[key] for r in rows], dtype=np.float64)
            entry[key] = float(np.average(values, weights=frames)) if rows else float("nan")
        result[label] = entry
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path, help="report.json of pointtrack eval --out")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--world-seed", type=int, default=0, help="synthetic world seed")
    parser.add_argument("--split", default="test")
    parser.add_argument("--setting", default="kitti-1")
    parser.add_argument("--by-category", action="store_true", help="a row per category too")
    args = parser.parse_args()

    from training.samples import load_tracklets

    tracklets, _, _ = load_tracklets(
        "synthetic",
        args.split,
        setting=args.setting,
        preset=args.preset,
        world_seed=args.world_seed,
        trained_only=False,
    )
    steps = {t.tracklet_id: mean_step_m(t.boxes) for t in tracklets}
    reports = json.loads(args.report.read_text())
    if "per_tracklet" in reports:  # a single tracker's report
        reports = {reports["tracker"]: reports}
    bins = [speed_bin(e) for e in BIN_EDGES_M]
    print("| tracker | category | " + " | ".join(f"{b} m/frame" for b in bins) + " |")
    print("|" + " --- |" * (len(bins) + 2))
    for name, report in reports.items():
        categories = [None]
        if args.by_category:
            categories += sorted({row["category"] for row in report["per_tracklet"]})
        for category in categories:
            result = breakdown(report, steps, category=category)
            cells = [
                f"{r['success']:.1f} / {r['precision']:.1f} ({r['tracklets']}, {r['frames']})"
                for r in result.values()
            ]
            print(f"| {name} | {category or 'all'} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
