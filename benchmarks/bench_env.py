"""Benchmark the Gymnasium env: zero-action steps/s through ``gymnasium.make``.

Usage: ``python benchmarks/bench_env.py [--quick] [--preset small] [--split test]``.

Prints, for the synthetic world ``--preset`` (generated into the cache if needed):

- cold: the first pass over every tracklet of the split (corridor indices built on the way);
- warm: later passes (best of ``--repeats``), the figure the issue asks >= 5,000 steps/s for;
- full scan: the same policy with ``corridor_m=None`` (every crop reads the whole scan), on the
  first ``--full-steps`` steps, and the warm / full-scan ratio (goal >= 20x);
- AsyncVectorEnv n = 1, 2 (module-qualified id, default start method): total steps/s after a
  warm-up pass per worker;
- uniform random actions over the whole action space (``--uniform-passes`` passes, best of
  them after a first one that builds the indices), against the zero-action warm figure of the
  same run (goal >= 0.5x), with how many crops the corridor, the whole-scan cell index and
  direct whole-scan crops served;
- memory of one env: the corridor cache's bytes after a full pass and the process RSS growth, on
  the ``default`` preset if that world is already generated, else on ``--preset``.

The machine is shared; numbers are best-of-N and the load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


CPU: dict[str, float] = {}


def zero_pass(
    env,
    max_steps: int | None = None,
    seed: int | None = 0,
    rng: np.random.Generator | None = None,
) -> tuple[int, float]:
    """Run every tracklet once with zero actions, or uniform random ones over the whole action
    space when ``rng`` is given (or stop after ``max_steps``) -> steps, wall s. The process CPU
    seconds of the pass are left in ``CPU["last"]``."""
    u = env.unwrapped
    zero = np.zeros(4, np.float32)
    low, high = env.action_space.low, env.action_space.high
    # drawn before the pass: the benchmark times the env, not the generator
    draws = None
    if rng is not None:
        n = sum(u.tracklet_lengths) if max_steps is None else max_steps
        draws = rng.uniform(low, high, (n, 4)).astype(np.float32)
    steps = 0
    start = time.perf_counter()
    cpu0 = time.process_time()
    for i in range(u.num_tracklets):
        env.reset(seed=seed if i == 0 else None, options={"tracklet": i})
        done = False
        while not done:
            action = zero if draws is None else draws[steps]
            _, _, term, trunc, _ = env.step(action)
            done = term or trunc
            steps += 1
            if max_steps is not None and steps >= max_steps:
                CPU["last"] = time.process_time() - cpu0
                return steps, time.perf_counter() - start
    CPU["last"] = time.process_time() - cpu0
    return steps, time.perf_counter() - start


def _cache_line(u) -> str:
    """What served the crops and the cache's size (also for the env before its whole-scan cell
    index, ``cache_stats`` without ``cell_index``, so a before / after comparison runs one
    script)."""
    stats = dict(u.cache_stats)
    return (
        f"  crops served by the corridor: {stats['corridor']}, by the whole-scan cell index: "
        f"{stats.get('cell_index', 0)}, direct whole-scan crops: {stats['full_scan']}; "
        f"cache {_cache_mib(u):.1f} MiB"
    )


def _cache_mib(u) -> float:
    nbytes = getattr(u, "cache_bytes", None)
    return (u._cache_bytes if nbytes is None else nbytes) / 2**20


def vector_rate(kwargs: dict, n: int, steps: int) -> float:
    """Total env steps/s of ``AsyncVectorEnv(n)`` over ``steps`` vector steps after warm-up."""
    import gymnasium as gym

    vec = gym.make_vec(
        "envs:pointtrack/Synthetic-v1", num_envs=n, vectorization_mode="async", **kwargs
    )
    try:
        lengths = vec.get_attr("tracklet_lengths")[0]
        warm = sum(length - 1 for length in lengths) + len(lengths)  # one pass per worker
        vec.reset(seed=0)
        actions = np.zeros((n, 4), np.float32)
        for _ in range(warm):
            vec.step(actions)
        start = time.perf_counter()
        for _ in range(steps):
            vec.step(actions)
        return n * steps / (time.perf_counter() - start)
    finally:
        vec.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and steps")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--sensor", default="hdl64")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--split", default="test")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--full-steps", type=int, default=300)
    parser.add_argument("--vector-steps", type=int, default=1000)
    parser.add_argument("--uniform-passes", type=int, default=3)
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats, args.full_steps, args.vector_steps = 1, 100, 200
        args.uniform_passes = 2

    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)
    from envs.synthetic import ensure_world

    kwargs = {"preset": args.preset, "sensor": args.sensor, "seed": args.seed, "split": args.split}
    t0 = time.perf_counter()
    root = ensure_world(args.preset, args.sensor, args.seed)
    print(f"world: {root} ({time.perf_counter() - t0:.1f} s to ensure)")
    print(f"load average: {os.getloadavg()[0]:.2f} (2 cores shared; numbers are best-of-N)")

    env = gym.make("pointtrack/Synthetic-v1", **kwargs)
    u = env.unwrapped
    print(f"split {args.split}: {u.num_tracklets} tracklets, {sum(u.tracklet_lengths)} frames")
    steps, secs = zero_pass(env)
    cold = steps / secs
    print(
        f"cold cache (first pass, indices built): {cold:9.0f} steps/s  ({steps} steps; "
        f"{steps / CPU['last']:.0f} per CPU-second)"
    )
    warm, warm_cpu = 0.0, 0.0
    for _ in range(args.repeats):
        steps, secs = zero_pass(env)
        warm, warm_cpu = max(warm, steps / secs), max(warm_cpu, steps / CPU["last"])
    print(
        f"warm cache (zero action, gymnasium.make): {warm:9.0f} steps/s  "
        f"({warm_cpu:.0f} per CPU-second)"
    )
    print(_cache_line(u))

    uni_env = gym.make("pointtrack/Synthetic-v1", **kwargs)
    rng = np.random.default_rng(args.seed)
    rates = []
    for _ in range(max(2, args.uniform_passes)):
        steps, secs = zero_pass(uni_env, rng=rng)
        rates.append((steps / secs, steps / CPU["last"]))
    cold_uni = rates[0][0]
    uniform, uniform_cpu = max(r[0] for r in rates[1:]), max(r[1] for r in rates[1:])
    print(
        f"uniform random actions (whole action space): {uniform:9.0f} steps/s warm "
        f"({uniform_cpu:.0f} per CPU-second), {cold_uni:.0f} on the first pass; "
        f"{uniform / warm:.2f}x the zero-action warm rate (goal >= 0.5x)"
    )
    print(_cache_line(uni_env.unwrapped))

    full_env = gym.make("pointtrack/Synthetic-v1", corridor_m=None, **kwargs)
    full, full_cpu = 0.0, 0.0
    for _ in range(max(1, args.repeats - 1)):
        steps, secs = zero_pass(full_env, args.full_steps)
        full, full_cpu = max(full, steps / secs), max(full_cpu, steps / CPU["last"])
    print(
        f"whole scan every step (corridor_m=None): {full:9.0f} steps/s  "
        f"({full_cpu:.0f} per CPU-second)"
    )
    print(f"warm / whole-scan speed-up: {warm / full:9.1f}x (CPU time: {warm_cpu / full_cpu:.1f}x)")

    for n in (1, 2):
        rate = vector_rate(kwargs, n, args.vector_steps // n)
        print(f"AsyncVectorEnv n={n}: {rate:9.0f} steps/s total")

    # memory of one env
    mem_preset = args.preset
    # the default world, if someone already generated it (never generated here: ~minutes)
    if any(root.parent.glob(f"default-{args.sensor}-s{args.seed}-*/label_02")):
        mem_preset = "default"
    rss0 = _rss_mb()
    mem_kwargs = dict(kwargs, preset=mem_preset)
    menv = gym.make("pointtrack/Synthetic-v1", **mem_kwargs)
    zero_pass(menv)
    mu = menv.unwrapped
    print(
        f"memory of one env ({mem_preset}, split {args.split}, after a full pass): corridor "
        f"cache {_cache_mib(mu):.1f} MiB, process RSS +{_rss_mb() - rss0:.1f} MiB, "
        f"pickled env {len(__import__('pickle').dumps(mu)) / 1024:.1f} KiB"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
