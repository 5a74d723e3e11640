"""Benchmark building KITTI tracklet lists from label + calibration files (no scans).

Usage: ``python benchmarks/bench_kitti.py [--quick] [--root PATH]``.

Default root: the real labels in ``../shared/kitti-tracking-labels`` next to the repository
(21 scenes). Without it, a synthetic set of 21 label files of the same size is written to a
temporary folder. Prints the best of several runs of ``KittiTracking(root, "all")`` (every
category) and of the four test-split category lists.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from envs.data import KittiTracking
from envs.data.kitti import Calibration, LabelRow, write_calibration, write_labels

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "kitti-tracking-labels"


def synthetic_labels(
    root: Path, scenes: int = 21, rows_per_scene: int = 3000, seed: int = 0
) -> Path:
    """Write ``scenes`` label + calibration files of ``rows_per_scene`` rows each."""
    rng = np.random.default_rng(seed)
    cats = ["Car", "Van", "Pedestrian", "Cyclist", "DontCare"]
    for s in range(scenes):
        rows = []
        for i in range(rows_per_scene):
            cam = [1.5, 1.6, 4.0, *rng.uniform(-20, 20, 3), rng.uniform(-3, 3)]
            rows.append(LabelRow.from_box(i // 10, i % 10, cats[i % 5], cam))
        write_labels(root / "label_02" / f"{s:04d}.txt", rows)
        write_calibration(root / "calib" / f"{s:04d}.txt", Calibration())
    return root


def best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one run instead of three")
    parser.add_argument("--root", type=Path, default=None)
    args = parser.parse_args(argv)
    repeat = 1 if args.quick else 3
    with tempfile.TemporaryDirectory() as tmp:
        root = args.root
        if root is None:
            root = SHARED if (SHARED / "label_02").is_dir() else synthetic_labels(Path(tmp))
        n_files = len(list((root / "label_02").glob("*.txt")))
        seconds, ds = best_of(lambda: KittiTracking(root, "all"), repeat)
        frames = sum(len(t) for t in ds.tracklets)
        print(
            f"KittiTracking(all): {n_files} label files, {len(ds.tracklets)} tracklets, "
            f"{frames} frames in {seconds:.3f} s (best of {repeat}; goal < 2 s) [{root}]"
        )
        for cat in ("Car", "Pedestrian", "Van", "Cyclist"):
            seconds, ds = best_of(lambda c=cat: KittiTracking(root, "test", [c]), repeat)
            frames = sum(len(t) for t in ds.tracklets)
            print(f"  test {cat}: {len(ds.tracklets)} tracklets, {frames} frames, {seconds:.3f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
