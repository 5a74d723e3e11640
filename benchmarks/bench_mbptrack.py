"""MBPTrack's batch-1 ``act`` CPU time next to P2B's, on synthetic-env observations.

    OMP_NUM_THREADS=1 python benchmarks/bench_mbptrack.py [--steps 40] [--repeats 3]
                                                          [--p2b p2b-kitti1-u] [--mbptrack FILE]

Observations: the ``small`` world's test split (KITTI-1 setting) with the env's opt-in memory
keys (3 frames), the episodes driven by zero actions (the previous-box baseline) so both trackers
see the same observations, acted on in episode order (as in tracking: each step's search region
comes back as memory, and MBPTrack's seed cache computes every frame's backbone once; a fresh
tracker per repeat, warmed on the first three). The figure is the median process CPU time per
``act`` call with one torch thread, best of ``--repeats`` interleaved runs (P2B, MBPTrack, P2B,
...): on a shared machine process time moves far less with the load than wall time. Without
``--mbptrack`` MBPTrack is untrained, at the slim and default widths. A line per MBPTrack gives
its backbone alone on the same search regions, every centre evaluated and each distinct point
once (the one-cloud path ``act`` takes).
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_m2track import act_cpu_ms, observations  # noqa: E402 - same folder

import trackers  # noqa: E402
from envs.spec import MEMORY_KEYS  # noqa: E402
from trackers import ops  # noqa: E402


def fresh_act_cpu_ms(model, observations: list[dict[str, np.ndarray]]) -> float:
    """``bench_m2track.act_cpu_ms`` on a fresh copy of ``model`` (an empty seed cache)."""
    return act_cpu_ms(copy.deepcopy(model), observations)


def backbone_cpu_ms(model, observations: list[dict[str, np.ndarray]], copies: bool) -> float:
    """Median process CPU milliseconds of ``model``'s backbone on each observation's search
    region in its eval (hash) order, with or without its one-cloud path that evaluates each
    distinct point once (``DGCNNBackbone(copies=...)``)."""
    seed = int(model.config.sampling_seed)
    cpu = []
    with torch.no_grad():
        for obs in observations:
            cloud = torch.from_numpy(np.asarray(obs["search"], np.float32))[None]
            ordered = ops.gather(cloud, ops.hash_order(cloud, seed))
            start = time.process_time()
            model.backbone(ordered, copies=copies)
            cpu.append(time.process_time() - start)
    return float(np.median(cpu) * 1e3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--p2b", default="p2b-kitti1-u", help="P2B checkpoint or name")
    parser.add_argument("--mbptrack", default=None, help="MBPTrack checkpoint (default: untrained)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    obs = observations(args.steps, MEMORY_KEYS)
    models = [(args.p2b, trackers.load(args.p2b, expect="p2b"))]
    if args.mbptrack:
        models.append((args.mbptrack, trackers.load(args.mbptrack, expect="mbptrack")))
    else:
        for size in ("slim", "default"):
            torch.manual_seed(0)
            model = trackers.make("mbptrack", **trackers.size_config("mbptrack", size)).eval()
            models.append((f"mbptrack {size} (untrained)", model))
    for _, model in models:  # warm-up: allocator, BatchNorm folds
        fresh_act_cpu_ms(model, obs[:3])
    best = {name: float("inf") for name, _ in models}
    for _ in range(args.repeats):  # interleaved: the machine's load hits every model alike
        for name, model in models:
            best[name] = min(best[name], fresh_act_cpu_ms(model, obs))
    for name, model in models[1:]:  # the backbone alone, distinct points once or every centre
        ms = {copies: min(backbone_cpu_ms(model, obs, copies) for _ in range(args.repeats))
              for copies in (False, True)}  # fmt: skip
        print(f"{name}: backbone {ms[False]:.2f} ms, each distinct point once {ms[True]:.2f} ms")
    base = best[models[0][0]]
    for name, ms in best.items():
        print(
            f"{name}: median act CPU {ms:.1f} ms ({base / ms:.2f}x P2B's frames/s), best of "
            f"{args.repeats} over {len(obs)} observations",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
