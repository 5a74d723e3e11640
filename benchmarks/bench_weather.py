"""Speed of the weather corruptions and of the weather hook in the env.

    python benchmarks/bench_weather.py [--quick]

Prints, for a 120k-point scan: ms per corruption at every level (median of repeats, the per-alpha
/ per-rate lookup tables already built; their one-off build time is printed separately), the
domain randomisation, and the env's cost per step clean vs under weather (corrupted scans cached
with the env's per-tracklet corridor cache: the first pass corrupts each frame once, the second
pass is all cache hits).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def random_scan(n: int = 120_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI-sized scan: rays of a 64-beam-like elevation band, ranges 2..120 m."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(np.radians(-24.9), np.radians(2.0), n)
    r = np.minimum(rng.exponential(25.0, n) + 2.0, 120.0)
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return (d * r[:, None]).astype(np.float32), rng.uniform(0.0, 1.0, n).astype(np.float32)


def median_ms(fn, repeats: int) -> float:
    """Median CPU time of ``fn`` in ms (process time: the corruptions are single-threaded numpy,
    and CPU time stays meaningful when other jobs share the cores; wall time is higher then)."""
    times = []
    for _ in range(repeats):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    return 1e3 * float(np.median(times))


def bench_corruptions(repeats: int) -> None:
    import envs.weather as w
    from envs.weather.fog import soft_target_table
    from envs.weather.precipitation import scatterer_table

    pts, inten = random_scan()
    print(f"corruptions on a {len(pts):,}-point scan (CPU ms, median of {repeats}):")
    for kind in w.KINDS:
        for level in w.LEVELS:
            p = w.parameter(kind, level)
            t = time.process_time()
            (soft_target_table(p) if kind == "fog" else scatterer_table(kind, p))
            table_ms = 1e3 * (time.process_time() - t)
            rng = np.random.default_rng(0)
            ms = median_ms(lambda k=kind, lv=level, g=rng: w.corrupt(k, pts, inten, g, lv), repeats)
            out, _ = w.corrupt(kind, pts, inten, np.random.default_rng(0), level)
            print(f"  {w.describe(kind, level):<36} {ms:6.1f} ms   kept {len(out) / len(pts):6.1%}"
                  f"   (one-off table {table_ms:5.1f} ms)")
    xyz = np.column_stack([pts, inten])
    for n in (len(xyz), 1024):
        sub = xyz[:n]
        rng = np.random.default_rng(0)
        def aug(s=sub, g=rng):
            return w.domain_randomize(s, g, p_skip=0.0, p_step=1.0)

        ms = median_ms(aug, repeats)
        print(f"  domain_randomize, all steps on, {n:>7,} points  {ms:6.2f} ms")


def bench_env(quick: bool) -> None:
    from envs.tracking_env import TrackingEnv, make_toy_dataset
    from envs.weather import WeatherWrapper

    frames = 10 if quick else 30
    ds = make_toy_dataset(categories=("Car", "Pedestrian"), num_frames=frames, num_clutter=120_000)
    print(f"env steps on 120k-point scans, {len(ds.tracklets)} tracklets x {frames} frames "
          "(CPU ms per step):")
    for label, make in (
        ("clean", lambda: TrackingEnv(ds)),
        ("rain L5", lambda: WeatherWrapper(TrackingEnv(ds), "rain", 5)),
        ("fog L5", lambda: WeatherWrapper(TrackingEnv(ds), "fog", 5)),
    ):
        env = make()
        row = []
        for _ in range(2):  # first pass fills the corridor cache, second is all hits
            steps, t = 0, time.process_time()
            for i in range(len(ds.tracklets)):
                env.reset(seed=0, options={"tracklet": i})
                done = False
                while not done:
                    _, _, done, _, _ = env.step(np.zeros(4, np.float32))
                    steps += 1
            row.append(1e3 * (time.process_time() - t) / steps)
        print(f"  {label:<8} first pass {row[0]:6.2f} ms/step   cached {row[1]:6.3f} ms/step")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and frames")
    args = parser.parse_args()
    bench_corruptions(3 if args.quick else 10)
    bench_env(args.quick)


if __name__ == "__main__":
    main()
