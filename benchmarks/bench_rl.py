"""Benchmark RL fine-tuning throughput: rollout steps/s and PPO update samples/s.

Usage: ``python benchmarks/bench_rl.py [--quick] [--threads N] [--tracker NAME]
[--num-envs 1,4,8] [--preset tiny]``.

For each number of sub-envs ``K`` it prints (a) the rollout rate: env steps/s of
``TrackerPolicy`` acting on a ``DummyVecEnv`` of ``K`` envs (one batch-``K`` tracker forward
under ``no_grad`` plus ``K`` env steps, the code path of PPO's ``collect_rollouts``), against
``tracker.act`` on the same batches (the policy's overhead), and (b) the update rate: samples/s
of ``evaluate_actions`` + backward + optimizer step on minibatches of 64 (train_parts ``head``
and ``all``). Data: the synthetic world of ``--preset`` (train split, kitti-1 observed
categories).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="K = 1, 4 and fewer steps")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--tracker", default="p2b-kitti1-u")
    parser.add_argument("--num-envs", default="1,4,8")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--steps", type=int, default=16, help="rollout steps per K")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from stable_baselines3.common.utils import obs_as_tensor

    from training.rl import TrackerPolicy
    from training.rl.config import FinetuneConfig
    from training.rl.run import train_env_factory
    from training.rl.wrappers import make_vec_env

    cfg = FinetuneConfig(tracker=args.tracker, preset=args.preset)
    factory = train_env_factory(cfg)
    ks = [1, 4] if args.quick else [int(k) for k in args.num_envs.split(",")]
    steps = 6 if args.quick else args.steps
    print(f"{args.tracker}, {args.threads} thread(s), world {args.preset}:")
    for k in ks:
        venv = make_vec_env(factory, k, cfg.clip_length)
        policy = TrackerPolicy(
            venv.observation_space, venv.action_space, lambda _: 3e-4, tracker=args.tracker
        )
        obs = venv.reset()
        batches, t_policy, t_env = [], 0.0, 0.0
        for _ in range(steps + 1):
            t0 = time.perf_counter()
            with torch.no_grad():
                actions, _, _ = policy(obs_as_tensor(obs, "cpu"))
            t1 = time.perf_counter()
            batches.append(obs)
            obs, _, _, _ = venv.step(actions.numpy())
            t2 = time.perf_counter()
            if len(batches) > 1:  # the first step warms up
                t_policy += t1 - t0
                t_env += t2 - t1
        t0 = time.perf_counter()
        for b in batches[1:]:
            policy.tracker.act(b)
        t_act = time.perf_counter() - t0
        n = steps * k
        print(
            f"  K={k}: rollout {n / (t_policy + t_env):.1f} steps/s (policy forward "
            f"{1e3 * t_policy / steps:.1f} ms/batch, tracker.act {1e3 * t_act / steps:.1f} "
            f"ms/batch, env {1e3 * t_env / n:.1f} ms/step)"
        )
        venv.close()
    pool = {key: np.concatenate([b[key] for b in batches]) for key in batches[0]}
    size = min(64, len(pool["search"]))
    mini = {key: torch.as_tensor(v[:size]) for key, v in pool.items()}
    for parts in ("head", "all"):
        policy = TrackerPolicy(
            venv.observation_space,
            venv.action_space,
            lambda _: 3e-4,
            tracker=args.tracker,
            train_parts=parts,
        )
        actions = torch.zeros(size, 4)
        times = []
        for _ in range(2 if args.quick else 3):
            t0 = time.perf_counter()
            values, logp, _ = policy.evaluate_actions(mini, actions)
            loss = -logp.mean() + values.square().mean()
            policy.optimizer.zero_grad()
            loss.backward()
            policy.optimizer.step()
            times.append(time.perf_counter() - t0)
        best = min(times[1:])
        print(
            f"  update ({parts}): {size / best:.1f} samples/s (minibatch {size}, "
            f"{1e3 * best:.0f} ms)"
        )


if __name__ == "__main__":
    main()
