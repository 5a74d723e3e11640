"""Speed of the weather corruptions and of the weather hook in the env; the fog rules and the
snow rates side by side on one scan; the weather benchmark's wall time.

    python benchmarks/bench_weather.py [--quick]
    python benchmarks/bench_weather.py --compare [--preset small]    # fog modes, snow rates
    python benchmarks/bench_weather.py --benchmark p2b-kitti1-u --num-envs 1 8 [--max-tracklets 8]

``--compare`` takes, of the first frames of the test tracklets at least 15 m away, the one with
the most target points of a synthetic world and prints, per fog rule at every level, the target
points left inside the ground-truth box, the points kept in the scan, and the ranges of the fog
returns; then the same for snow at the benchmark's rates (the rain rates) and at 0.5-2.5 mm/h.
``--benchmark`` times ``run_weather_benchmark`` of one tracker over clean + fog L5 (no analysis)
on the preset's test split per ``--num-envs`` (wall and process CPU time; the process time
stays meaningful when other jobs share the cores) and extrapolates to the 16 conditions.

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
            print(
                f"  {w.describe(kind, level):<36} {ms:6.1f} ms   kept {len(out) / len(pts):6.1%}"
                f"   (one-off table {table_ms:5.1f} ms)"
            )
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
    print(
        f"env steps on 120k-point scans, {len(ds.tracklets)} tracklets x {frames} frames "
        "(CPU ms per step):"
    )
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


def compare_rules(preset: str) -> None:
    """Fog reference vs lossy and snow at the two rate sets, on one synthetic test scan."""
    from envs.geometry import points_in_box
    from envs.tracking_env import make_synthetic_env
    from envs.weather.fog import fog_alpha
    from envs.weather.levels import (
        FOG_ALPHA_PER_M,
        RAIN_RATE_MM_H,
        SNOW_RATE_MM_H_HAHNER,
    )
    from envs.weather.precipitation import precipitation_rate

    env = make_synthetic_env(preset=preset, split="test", setting="kitti-1")
    # a target where fog matters: of the frames 0 of the test tracklets at least 15 m away, the
    # one with the most points in its box (a near car keeps its points under any fog level)
    best = None
    for tr in env.tracklets:
        box = np.asarray(tr.boxes[0], dtype=np.float64)
        if float(np.linalg.norm(box[:2])) < 15.0:
            continue
        scan = np.asarray(tr.points_with_intensity(0), dtype=np.float32)
        n_target = int(points_in_box(scan[:, :3], box).sum())
        if best is None or n_target > best[0]:
            best = (n_target, tr, scan, box)
    n_target, tr, scan, box = best
    dist = float(np.linalg.norm(box[:2]))
    print(
        f"{preset} test tracklet {tr.tracklet_id} ({tr.category}) frame 0: {len(scan):,} points,"
        f" {n_target} in the target box at {dist:.1f} m"
    )
    pts, inten = scan[:, :3], scan[:, 3]
    r_in = np.linalg.norm(pts, axis=1)
    for mode in ("reference", "lossy"):
        print(f"  fog, {mode} rule:")
        for level, alpha in enumerate(FOG_ALPHA_PER_M, start=1):
            out, _, src = fog_alpha(
                pts, inten, np.random.default_rng(0), alpha, return_source=True, mode=mode
            )
            r_out = np.linalg.norm(out, axis=1)
            fog = r_out < r_in[src] - 0.5
            in_box = int(points_in_box(out, box).sum())
            q = np.percentile(r_out[fog], [5, 50, 95]) if fog.any() else [np.nan] * 3
            print(
                f"    L{level} alpha {alpha:<5g}: target {in_box:4d}/{n_target}  scan kept "
                f"{len(out) / len(pts):6.1%}  fog returns {int(fog.sum()):6,} at "
                f"{q[0]:.1f} / {q[1]:.1f} / {q[2]:.1f} m (5/50/95 %)"
            )
    for label, rates in (
        ("benchmark (rain rates)", RAIN_RATE_MM_H),
        ("Hahner 0.5-2.5", SNOW_RATE_MM_H_HAHNER),
    ):
        print(f"  snow, {label}:")
        for level, rate in enumerate(rates, start=1):
            out, _, src = precipitation_rate(
                pts, inten, np.random.default_rng(0), "snow", rate, return_source=True
            )
            r_out = np.linalg.norm(out, axis=1)
            flakes = int((r_out < r_in[src] - 0.5).sum())
            in_box = int(points_in_box(out, box).sum())
            print(
                f"    L{level} {rate:<6g} mm/h: target {in_box:4d}/{n_target}  scan kept "
                f"{len(out) / len(pts):6.1%}  snowflake returns {flakes:6,}"
            )


def bench_benchmark(
    tracker_name: str, preset: str, counts: list[int], max_tracklets: int | None = None
) -> None:
    """Wall and CPU seconds of clean + fog L5 per --num-envs (on the first ``max_tracklets``
    test tracklets if given), extrapolated to the 16 conditions of the whole test split by the
    frame count."""
    import torch

    from envs.tracking_env import make_synthetic_env
    from training.evaluate import env_options_for
    from training.loading import load_tracker
    from training.robustness import run_weather_benchmark

    torch.set_num_threads(1)
    tracker = load_tracker(tracker_name)
    base = make_synthetic_env(
        preset=preset, split="test", setting="kitti-1", **env_options_for([tracker])
    )
    subset = None if max_tracklets is None else list(range(min(max_tracklets, base.num_tracklets)))
    total = sum(base.tracklet_lengths)
    print(
        f"{tracker_name}, {preset} test ({base.num_tracklets} tracklets, {total} frames), "
        f"clean + fog L5 on {len(subset) if subset else base.num_tracklets} tracklets:"
    )
    for n in counts:
        wall, cpu = time.perf_counter(), time.process_time()
        res = run_weather_benchmark(
            tracker,
            base.clone,
            ("fog",),
            (5,),
            num_envs=n if n > 1 else None,
            tracklets=subset,
            analysis=False,
        )
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        frames = res["clean"]["frames"]
        per_frame = cpu / (2 * frames)
        print(
            f"  --num-envs {n:>2}: {wall:6.1f} s wall, {cpu:6.1f} s CPU for 2 x {frames} "
            f"frames = {1e3 * per_frame:.1f} ms CPU/frame -> 16 conditions x {total} frames "
            f"~{16 * total * per_frame / 60:.1f} min CPU"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and frames")
    parser.add_argument(
        "--compare",
        action="store_true",
        help="fog rules and snow rates side by side on one synthetic scan",
    )
    parser.add_argument("--benchmark", metavar="TRACKER", help="time the weather benchmark")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 8, 16])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--max-tracklets", type=int, default=None)
    args = parser.parse_args()
    if args.compare:
        compare_rules(args.preset)
        return
    if args.benchmark:
        bench_benchmark(args.benchmark, args.preset, args.num_envs, args.max_tracklets)
        return
    bench_corruptions(3 if args.quick else 10)
    bench_env(args.quick)


if __name__ == "__main__":
    main()
