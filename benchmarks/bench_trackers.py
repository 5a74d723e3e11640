"""Tracker benchmark: the shipped kitti-1 files' ``act`` and network, randomly initialised
models' forward at batch 1 and 32, a training step, and farthest-point sampling / ball query
against naive references.

    python benchmarks/bench_trackers.py [--quick] [--threads 1] [--device cpu|cuda]
        [--sections shipped,random,eval,ops] [--files kitti1|NAME,...] [--observations 24]
        [--env-steps 300] [--trackers p2b m2track] [--model-size default|slim]
        [--baseline REV [--rounds 3]]

``shipped``: for every shipped kitti-1 checkpoint (``--files``), frames/s of a batch-1 ``act``
as shipped (hold and re-ranking included) and of its network alone (``eval_forward``), over
``--observations`` recorded observations of moving targets (synthetic ``small`` world, test
split, kitti-1 setting, driven by the ``constant_velocity`` baseline: the same observations for
every file and every commit; a frame counts as moving when its ground-truth box moved more than
0.2 m), best of ``--repeats`` passes. ``ops``: FPS 1024 -> 512 and the ball query, calls/s.
These two sections are what ``--baseline REV`` compares (``benchmarks/baseline.py``).

``random`` (toy inputs from ``trackers.toy.toy_batch``, untrained weights; M2-Track's eval cost
depends on how many points its segmentation keeps, so a trained model's time differs): forward
times in eval mode under ``torch.inference_mode``; "act" adds observation validation and the
numpy round trip; "CPU" is this process's CPU time per call. ``--env-steps N`` also times
``act`` on N synthetic-env observations, each tracker acting on its own.

``eval`` (``--eval-batch B``, default 8 as ``pointtrack eval --num-envs 8``): for each shipped
``-u`` checkpoint, milliseconds per frame of an eval forward of ``B`` observations (half of them
env-like padded clouds) as shipped (fast path, batch-invariant: one sample at a time), batched
(``batch_invariant = False``) and on the plain path (``fast_eval = False``).
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch
from baseline import best_seconds, parser, run, use_code_root

use_code_root()

import trackers  # noqa: E402
from trackers import ops  # noqa: E402
from trackers.toy import toy_batch  # noqa: E402

CPU_TIMES: list[float] = []


def timeit(fn, reps: int, warmup: int = 1, sync=lambda: None) -> float:
    """Median wall seconds per call (the median process CPU seconds go to ``CPU_TIMES``)."""
    for _ in range(warmup):
        fn()
    sync()
    times, cpu = [], []
    for _ in range(reps):
        t, c = time.perf_counter(), time.process_time()
        fn()
        sync()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    times.sort()
    cpu.sort()
    CPU_TIMES.append(cpu[len(cpu) // 2])
    return times[len(times) // 2]


def naive_fps(xyz: torch.Tensor, n: int) -> torch.Tensor:
    """Reference FPS: one batch row at a time, one point at a time."""
    out = []
    for row in xyz:
        chosen = [0]
        mind = torch.full((row.shape[0],), float("inf"))
        for _ in range(n - 1):
            mind = torch.minimum(mind, (row - row[chosen[-1]]).square().sum(-1))
            chosen.append(int(mind.argmax()))
        out.append(chosen)
    return torch.tensor(out)


def naive_ball_query(radius: float, k: int, xyz: torch.Tensor, centres: torch.Tensor):
    """Reference ball query: one centre at a time."""
    out = torch.zeros(*centres.shape[:2], k, dtype=torch.long)
    for b in range(xyz.shape[0]):
        for m in range(centres.shape[1]):
            hits = torch.nonzero((xyz[b] - centres[b, m]).square().sum(-1) < radius * radius)[:, 0]
            hits = hits[:k]
            if len(hits):
                out[b, m] = hits[0]
                out[b, m, : len(hits)] = hits
    return out


def motion_batch(batch_size: int, seed: int) -> tuple[dict, dict]:
    """M2-Track's inputs and targets from a toy batch: the previous frame is the search region
    with the target 0.4 m behind (the whole cloud shifted: a timing input, not a scene)."""
    batch, targets = toy_batch(batch_size, seed=seed)
    shift = torch.tensor([0.4, 0.0, 0.0])
    box = targets["search_box"][:, [0, 1, 2, 6]]
    inputs = {
        "search": batch["search"],
        "previous_search": batch["search"] - shift,
        "size": batch["size"],
        "prior_is_gt": torch.ones(batch_size),
    }
    labels = targets["search_labels"]
    return inputs, {
        "seg_labels": torch.cat([labels, labels], dim=1),
        "box": box,
        "prev_box": box - torch.cat([shift, torch.zeros(1)]),
        "motion_box": torch.cat([shift, torch.zeros(1)]).expand(batch_size, 4),
        "moving": torch.ones(batch_size),
    }


def tracker_inputs(model, batch_size: int, seed: int) -> tuple[dict, dict]:
    """The forward inputs and loss targets of ``model`` (M2-Track reads two frames)."""
    if "previous_search" in getattr(model, "observation_keys", ()):
        return motion_batch(batch_size, seed)
    return toy_batch(batch_size, seed=seed)


def one_observation(model, seed: int) -> dict:
    batch, _ = toy_batch(1, seed=seed)
    obs = {k: v[0].numpy() for k, v in batch.items()}
    if "previous_search" in getattr(model, "observation_keys", ()):
        obs["previous_search"] = motion_batch(1, seed)[0]["previous_search"][0].numpy()
    return obs


def env_act_ms(model, steps: int) -> float:
    """Median wall milliseconds of ``model.act`` over ``steps`` synthetic-env observations
    (the tracker's own actions drive the episodes; env time excluded)."""
    from envs.tracking_env import make_synthetic_env
    from training.evaluate import observation_keys_for

    env = make_synthetic_env(
        preset="small",
        split="test",
        setting="kitti-1",
        observation_keys=observation_keys_for([model]),
    )
    obs, _ = env.reset(seed=0)
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        action = model.act(obs)
        times.append(time.perf_counter() - t)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset()
    times.sort()
    return times[len(times) // 2] * 1e3


def padded(batch: dict[str, torch.Tensor], seed: int) -> dict[str, torch.Tensor]:
    """Every other row an env-like sparse cloud: 40 / 150 distinct points padded by copies."""
    g = torch.Generator().manual_seed(seed)
    out = {k: v.clone() for k, v in batch.items()}
    for row in range(0, out["template"].shape[0], 2):
        for key, distinct in (("template", 40), ("search", 150)):
            n = out[key].shape[1]
            out[key][row] = out[key][row, torch.randint(0, distinct, (n,), generator=g)]
    return out


def eval_modes(bsz: int, reps: int, device: torch.device, sync) -> None:
    """Milliseconds per frame of eval forwards: shipped, batched (not batch-invariant), plain."""
    batch = {k: v.to(device) for k, v in padded(toy_batch(bsz, seed=4)[0], seed=5).items()}
    for name in ("p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u"):
        model = trackers.load(name, map_location=device)
        row = {}
        for mode, invariant, fast in (
            ("shipped", True, True),
            ("batched", False, True),
            ("plain", True, False),
        ):
            model.batch_invariant, model.fast_eval = invariant, fast
            with torch.inference_mode():
                row[mode] = timeit(lambda m=model: m(batch), reps, sync=sync) * 1e3 / bsz
        model.batch_invariant, model.fast_eval = True, True
        print(
            f"{name} eval, batch {bsz}, ms/frame: per-sample (shipped) {row['shipped']:.1f} | "
            f"batched {row['batched']:.1f} (batch invariance costs "
            f"{100 * (row['shipped'] / row['batched'] - 1):+.0f} %) | plain path "
            f"{row['plain']:.1f} ({row['plain'] / row['shipped']:.1f}x the fast path)"
        )


def moving_observations(count: int, keys: tuple[str, ...]) -> list[dict[str, np.ndarray]]:
    """``count`` observations of moving targets (see the module doc), in a fixed order."""
    from envs.tracking_env import make_synthetic_env
    from trackers.baselines import ConstantVelocity

    env = make_synthetic_env(preset="small", split="test", setting="kitti-1", observation_keys=keys)
    policy = ConstantVelocity(init="points")
    out: list[dict[str, np.ndarray]] = []
    for tracklet in range(env.num_tracklets):
        obs, _ = env.reset(seed=tracklet, options={"tracklet": tracklet})
        prev_gt, done = None, False
        while not done and len(out) < count:
            following, _, terminated, truncated, info = env.step(policy.act(obs))
            gt = info["gt_box"]  # the box of the frame ``obs`` showed
            if prev_gt is not None and np.linalg.norm(gt[:3] - prev_gt[:3]) > 0.2:
                out.append(obs)
            obs, prev_gt, done = following, gt, terminated or truncated
        if len(out) >= count:
            break
    if len(out) < count:
        raise SystemExit(f"only {len(out)} moving observations in the small test split")
    return out


def shipped_rates(
    files: list[str], count: int, repeats: int, clock: str = "wall"
) -> dict[str, float]:
    """Batch-1 frames/s of ``act`` (as shipped) and of the network alone for each file."""
    from training.evaluate import observation_keys_for

    models = {name: trackers.load(name) for name in files}
    observations = moving_observations(count, observation_keys_for(list(models.values())))
    rates = {}
    for name, model in models.items():
        obs = observations
        prepared = [model.prepare(o)[0] for o in obs]

        def act(m=model, obs=obs):
            for o in obs:
                m.act(o)

        def network(m=model, batches=prepared):
            with torch.no_grad():
                for b in batches:
                    m.eval_forward(b)

        rates[f"{name} act"] = count / best_seconds(act, repeats, clock=clock)
        rates[f"{name} network"] = count / best_seconds(network, repeats, clock=clock)
    return rates


def ops_rates(repeats: int, clock: str = "wall") -> dict[str, float]:
    """Calls/s of FPS 1024 -> 512 and of the ball query (512 x 1024, r 0.3, k 32), batch 1."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 1024, 3, generator=g) * torch.tensor([9.0, 6.0, 3.0])
    return {
        "FPS 1024->512 b1": 1
        / best_seconds(lambda: ops.farthest_point_sample(x, 512), repeats, clock=clock),
        "ball query b1": 1
        / best_seconds(lambda: ops.ball_query_pairs(0.3, 32, x, x[:, :512]), repeats, clock=clock),
    }


def kitti1_files() -> list[str]:
    """The shipped kitti-1 checkpoints of P2B, BAT, GPT and M2-Track."""
    kinds = ("p2b-", "bat-", "gpt-", "m2track-")
    return [n for n in trackers.available("checkpoint") if "-kitti1" in n and n.startswith(kinds)]


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__, threads=1, repeats=3)
    p.add_argument("--quick", action="store_true", help="fewer repetitions, batch 8 not 32")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--sections",
        help="comma-separated of shipped, random, eval, ops (default: all; with --baseline: "
        "shipped,ops)",
    )
    p.add_argument("--files", default="kitti1", help="shipped files: kitti1 (all) or NAME,...")
    p.add_argument("--observations", type=int, default=24, help="moving observations (shipped)")
    p.add_argument("--trackers", nargs="*", default=["p2b", "bat", "gpt", "m2track"])
    p.add_argument("--model-size", default="default", help="default | slim")
    p.add_argument(
        "--eval-batch", type=int, default=8, help="batch of the eval-mode comparison (0: skip it)"
    )
    p.add_argument(
        "--env-steps",
        type=int,
        default=0,
        help="also time act() on this many synthetic-env observations",
    )
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    default = "shipped,ops" if args.baseline or args.json_out else "shipped,random,eval,ops"
    sections = set((args.sections or default).split(","))
    unknown = sections - {"shipped", "random", "eval", "ops"}
    if unknown:
        raise SystemExit(f"--sections: unknown {sorted(unknown)}; valid: shipped,random,eval,ops")
    files = kitti1_files() if args.files == "kitti1" else args.files.split(",")
    print(
        f"torch {torch.__version__}, {trackers.__file__}, threads {torch.get_num_threads()}, "
        f"load average {os.getloadavg()[0]:.2f}"
    )
    if "random" in sections or "eval" in sections:
        random_models(args, sections)

    def measure() -> dict[str, float]:
        rates = {}
        if "shipped" in sections:
            rates.update(shipped_rates(files, args.observations, args.repeats, args.clock))
        if "ops" in sections:
            rates.update(ops_rates(max(args.repeats, 5), args.clock))
        return rates

    return run(args, measure, "per s")


def random_models(args, sections: set[str]) -> None:
    """The ``random`` and ``eval`` sections (printed) and the ops against naive references."""
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    reps = 3 if args.quick else 10
    big = 8 if args.quick else 32
    results = {}
    for name in args.trackers if "random" in sections else []:
        torch.manual_seed(0)
        model = trackers.make(name, **trackers.size_config(name, args.model_size))
        model = model.to(device).eval()
        params = sum(p.numel() for p in model.parameters())
        row = {"params": params}
        for bsz in (1, big):
            batch, _ = tracker_inputs(model, bsz, seed=1)
            batch = {k: v.to(device) for k, v in batch.items()}
            with torch.inference_mode():
                dt = timeit(lambda b=batch, m=model: m(b), reps, sync=sync)
            row[f"ms_b{bsz}"] = dt * 1e3
            row[f"cpu_ms_b{bsz}"] = CPU_TIMES[-1] * 1e3
            row[f"fps_b{bsz}"] = bsz / dt
        obs = one_observation(model, seed=2)
        row["act_ms"] = timeit(lambda o=obs, m=model: m.act(o), reps) * 1e3
        batch, targets = tracker_inputs(model, 8, seed=3)
        batch = {k: v.to(device) for k, v in batch.items()}
        targets = {k: v.to(device) for k, v in targets.items()}
        model.train()

        def step(m=model, b=batch, t=targets):
            m.zero_grad(set_to_none=True)
            m.loss(m(b), t)["total"].mean().backward()

        row["train_ms_b8"] = timeit(step, max(1, reps // 3), sync=sync) * 1e3
        model.eval()
        env_note = ""
        if args.env_steps > 0:
            row["env_act_ms"] = env_act_ms(model, args.env_steps)
            env_note = f" | act on env obs {row['env_act_ms']:6.1f} ms"
        results[name] = row
        print(
            f"{name:7s} params {params / 1e6:.2f} M | batch 1: {row['ms_b1']:7.1f} ms "
            f"(CPU {row['cpu_ms_b1']:6.1f} ms, {row['fps_b1']:5.1f} frames/s) | "
            f"batch {big}: {row[f'ms_b{big}']:8.1f} ms "
            f"({row[f'fps_b{big}']:6.1f} frames/s) | act(1 obs) {row['act_ms']:6.1f} ms | "
            f"train step b8 {row['train_ms_b8']:7.1f} ms{env_note}"
        )
    if "p2b" in results:
        base = results["p2b"]["fps_b1"]
        print(
            "frames/s at batch 1 relative to P2B: "
            + ", ".join(f"{n} {r['fps_b1'] / base:.2f}x" for n, r in results.items())
        )

    if "eval" in sections and args.eval_batch > 0:
        eval_modes(args.eval_batch, reps, device, sync)

    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(8, 1024, 3, generator=g) * torch.tensor([9.0, 6.0, 3.0])
    centres = xyz[:, :512]
    for bsz in (1, 8):
        x, c = xyz[:bsz], centres[:bsz]
        fast_idx, naive_idx = ops.farthest_point_sample(x, 512), naive_fps(x, 512)
        assert torch.equal(fast_idx, naive_idx)
        t_fast = timeit(lambda x=x: ops.farthest_point_sample(x, 512), reps)
        t_naive = timeit(lambda x=x: naive_fps(x, 512), 1, warmup=0)
        print(
            f"FPS 1024->512, batch {bsz}: {t_fast * 1e3:.1f} ms (naive per-row loop "
            f"{t_naive * 1e3:.1f} ms, {t_naive / t_fast:.1f}x)"
        )
        assert torch.equal(ops.ball_query(0.3, 32, x, c), naive_ball_query(0.3, 32, x, c))
        t_fast = timeit(lambda x=x, c=c: ops.ball_query(0.3, 32, x, c), reps)
        t_naive = timeit(lambda x=x, c=c: naive_ball_query(0.3, 32, x, c), 1, warmup=0)
        t_pairs = timeit(lambda x=x, c=c: ops.ball_query_pairs(0.3, 32, x, c), reps)
        print(
            f"ball query 512 centres x 1024 points (r 0.3, k 32), batch {bsz}: "
            f"{t_fast * 1e3:.2f} ms padded (naive per-centre loop {t_naive * 1e3:.1f} ms, "
            f"{t_naive / t_fast:.0f}x); {t_pairs * 1e3:.2f} ms as the ragged pairs the "
            f"backbone uses in eval"
        )


if __name__ == "__main__":
    raise SystemExit(main())
