"""Benchmark the still-target test and the re-ranking (``InferenceConfig.hold_chamfer_m``,
``rerank_top_k``: :mod:`trackers.decision`) against the network.

Usage: ``python benchmarks/bench_hold.py [--tracker bat-kitti1-u] [--batch 8] [--threads 1]
[--rerank-top-k 4]``.

Prints, on ``--batch`` observations of the synthetic ``default`` world's world-1 val split (one
zero-action step into ``--batch`` tracklets; generated into the cache if needed), best of
``--repeats``:

- ``keeps_box``: the test alone (two Chamfer distances per observation);
- ``act`` with the hold off: the network on every observation;
- ``act`` with the tracker's own hold: the network on the observations not held;
- ``choose_action`` with ``--rerank-top-k`` on the network's outputs for every observation: the
  re-ranking alone (``K + 1`` Chamfer distances per observation);
- ``act`` with the tracker's own hold and that re-ranking.

The machine is shared; numbers are best-of-N and the load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np
import torch

import trackers
from envs.tracking_env import make_synthetic_env
from trackers.base import prepare_observation
from trackers.decision import InferenceConfig, choose_action, keeps_box


def best_ms(fn: Callable[[], object], repeats: int) -> float:
    """Best wall time of ``repeats`` calls after one warm-up, milliseconds."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * min(times)


def observations(batch: int) -> dict[str, np.ndarray]:
    """One zero-action step into each of the first ``batch`` tracklets, stacked ``(B, ...)``."""
    env = make_synthetic_env(preset="default", seed=1, split="val", setting="kitti-1")
    obs = []
    for i in range(batch):
        env.reset(seed=i, options={"tracklet": i})
        o, *_ = env.step(np.zeros(4, np.float32))
        obs.append(o)
    return {k: np.stack([o[k] for o in obs]) for k in obs[0]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracker", default="bat-kitti1-u")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rerank-top-k", type=int, default=4)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    tracker = trackers.load(args.tracker)
    own = tracker.inference
    hold, k = own.hold_chamfer_m, args.rerank_top_k
    rerank = InferenceConfig(hold_chamfer_m=hold, rerank_top_k=k)
    batch = observations(args.batch)
    prepared = prepare_observation(batch)[0]
    held = int(keeps_box(tracker, prepared, own).sum())
    test_ms = best_ms(lambda: keeps_box(tracker, prepared, own), args.repeats)

    def act_ms(inference: InferenceConfig) -> float:
        tracker.inference = inference
        return best_ms(lambda: tracker.act(batch), args.repeats)

    held_ms = act_ms(InferenceConfig(hold_chamfer_m=hold))
    with torch.no_grad():
        outputs = tracker.eval_forward(prepared)
    max_action = tracker.max_action
    rerank_ms = best_ms(
        lambda: choose_action(tracker, prepared, outputs, rerank, max_action), args.repeats
    )
    both_ms = act_ms(rerank)
    plain_ms = act_ms(InferenceConfig())
    tracker.inference = own
    b = args.batch
    print(f"{args.tracker}, B = {b}, {args.threads} thread(s), load {os.getloadavg()[0]:.2f}")
    rows = [
        ("keeps_box", test_ms),
        ("act, hold off", plain_ms),
        (f"act, hold {hold:.2f} ({held} held)", held_ms),
        (f"choose_action, top {k}", rerank_ms),
        (f"act, hold {hold:.2f}, top {k}", both_ms),
    ]
    for label, ms in rows:
        print(f"{label:<28} {ms:7.1f} ms ({ms / b:.2f} ms / observation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
