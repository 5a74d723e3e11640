"""Benchmark oriented IoU: ``iou_3d`` on many random pairs vs a per-pair Shapely loop.

Usage: ``python benchmarks/bench_geometry.py [--quick] [--pairs N] [--shapely N]``.

Pairs: ``a`` has its centre uniform in a 20 m square, size l, w, h uniform in [0.5, 5] m and a
uniform yaw; ``b`` is ``a`` moved by N(0, 1 m) in x, y and N(0, 0.3 m) in z, its size scaled by
U(0.8, 1.2) and given an independent uniform yaw — the kind of pairs a tracker produces, most of
them overlapping (the fraction is printed). Prints pairs/s of ``iou_3d`` (best of 3 runs), the
Shapely per-pair loop's pairs/s on a subset, their ratio, the max |difference| on that subset and
the single-pair latency in microseconds.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from envs.geometry import iou_3d, iou_bev


def random_pairs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 7)`` and ``(n, 7)`` boxes as described in the module docstring."""
    rng = np.random.default_rng(seed)
    a = np.empty((n, 7))
    a[:, 0:2] = rng.uniform(-10, 10, (n, 2))
    a[:, 2] = rng.uniform(-2, 2, n)
    a[:, 3:6] = rng.uniform(0.5, 5.0, (n, 3))
    a[:, 6] = rng.uniform(-np.pi, np.pi, n)
    b = a.copy()
    b[:, 0:2] += rng.normal(0, 1.0, (n, 2))
    b[:, 2] += rng.normal(0, 0.3, n)
    b[:, 3:6] *= rng.uniform(0.8, 1.2, (n, 3))
    b[:, 6] = rng.uniform(-np.pi, np.pi, n)
    return a, b


def shapely_iou_3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Reference IoU, one Shapely intersection per pair in a Python loop.

    Corners are computed vectorised beforehand, so the loop times Shapely itself (polygon
    construction, intersection, area) plus the vertical overlap, as a careful user would write it.
    """
    from shapely.geometry import Polygon

    from envs.geometry import box_corners

    ca = box_corners(a)[:, :4, :2]
    cb = box_corners(b)[:, :4, :2]
    out = np.empty(len(a))
    for i in range(len(a)):
        inter = Polygon(ca[i]).intersection(Polygon(cb[i])).area
        za, ha, zb, hb = a[i, 2], a[i, 5], b[i, 2], b[i, 5]
        dz = min(za + ha / 2, zb + hb / 2) - max(za - ha / 2, zb - hb / 2)
        inter *= max(dz, 0.0)
        union = a[i, 3] * a[i, 4] * ha + b[i, 3] * b[i, 4] * hb - inter
        out[i] = inter / union
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100k pairs, 2k Shapely pairs")
    parser.add_argument("--pairs", type=int, default=None)
    parser.add_argument("--shapely", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    n = args.pairs or (100_000 if args.quick else 1_000_000)
    n_shapely = args.shapely or (2_000 if args.quick else 20_000)
    a, b = random_pairs(n)

    iou_3d(a[:1000], b[:1000])  # warm up
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        ious = iou_3d(a, b)
        times.append(time.perf_counter() - t0)
    best = min(times)
    rate = n / best
    print(
        f"iou_3d: {n} pairs in {best:.3f} s (best of {args.repeat}; "
        f"all {[round(t, 3) for t in times]}) -> {rate:,.0f} pairs/s; "
        f"overlapping fraction {np.mean(ious > 0):.3f}"
    )
    t0 = time.perf_counter()
    iou_bev(a, b)
    print(f"iou_bev: {n / (time.perf_counter() - t0):,.0f} pairs/s")

    t0 = time.perf_counter()
    ref = shapely_iou_3d(a[:n_shapely], b[:n_shapely])
    shapely_rate = n_shapely / (time.perf_counter() - t0)
    diff = float(np.abs(ref - ious[:n_shapely]).max())
    print(
        f"shapely loop: {shapely_rate:,.0f} pairs/s on {n_shapely} pairs; "
        f"speed ratio {rate / shapely_rate:.1f}x; max |diff| {diff:.2e}"
    )

    reps = 2_000
    t0 = time.perf_counter()
    for i in range(reps):
        iou_3d(a[i], b[i])
    single = (time.perf_counter() - t0) / reps * 1e6
    print(f"single pair: {single:.1f} us per call")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
