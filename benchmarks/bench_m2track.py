"""M2-Track's batch-1 ``act`` CPU time next to P2B's, on synthetic-env observations.

    OMP_NUM_THREADS=1 python benchmarks/bench_m2track.py [--steps 40] [--p2b p2b-kitti1-u]
                                                         [--m2track CHECKPOINT]

Observations: the ``small`` world's test split (KITTI-1 setting), the previous frame from the
env's opt-in ``previous_search`` key, the episodes driven by zero actions (the previous-box
baseline) so both trackers see the same observations. The figure is the median process CPU time
per ``act`` call with one torch thread: on a shared machine it moves far less with the load than
wall time. Without ``--m2track`` the M2-Track models are untrained (default and slim widths);
their cost depends on how many points the segmentation keeps, so a trained model's differs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import trackers  # noqa: E402
from envs.tracking_env import OBSERVATION_KEYS, make_synthetic_env  # noqa: E402


def observations(
    steps: int, keys: tuple[str, ...] = ("previous_search",)
) -> list[dict[str, np.ndarray]]:
    """``steps`` observations with the opt-in ``keys``, in episode order (zero actions)."""
    env = make_synthetic_env(
        preset="small",
        split="test",
        setting="kitti-1",
        observation_keys=(*OBSERVATION_KEYS, *keys),
    )
    obs, _ = env.reset(seed=0)
    out = []
    for _ in range(steps):
        out.append(obs)
        obs, _, terminated, truncated, _ = env.step(np.zeros(4, np.float32))
        if terminated or truncated:
            obs, _ = env.reset()
    return out


def act_cpu_ms(model, observations: list[dict[str, np.ndarray]]) -> float:
    """Median process CPU milliseconds of ``model.act`` (three warm-up calls first)."""
    for obs in observations[:3]:
        model.act(obs)
    cpu = []
    for obs in observations:
        start = time.process_time()
        model.act(obs)
        cpu.append(time.process_time() - start)
    return float(np.median(cpu) * 1e3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--p2b", default="p2b-kitti1-u", help="P2B checkpoint or name")
    parser.add_argument("--m2track", default=None, help="M2-Track checkpoint (default: untrained)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    obs = observations(args.steps)
    models = [(args.p2b, trackers.load(args.p2b, expect="p2b"))]
    if args.m2track:
        models.append((args.m2track, trackers.load(args.m2track, expect="m2track")))
    else:
        for size in ("default", "slim"):
            model = trackers.make("m2track", **trackers.size_config("m2track", size)).eval()
            models.append((f"m2track {size} (untrained)", model))
    base = None
    for name, model in models:
        ms = act_cpu_ms(model, obs)
        base = base or ms
        print(
            f"{name}: median act CPU {ms:.1f} ms ({base / ms:.2f}x P2B's frames/s) over "
            f"{len(obs)} observations",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
