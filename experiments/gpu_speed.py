"""Speed of the learned trackers' loops on one device, as JSON: ``act`` frames/s at batch 1 and
32, eval frames/s, finetune env steps/s and training samples/s (experiments/gpu_speed.sh runs it
on the GPU and on the CPU and writes the Markdown table).

    python experiments/gpu_speed.py --device cuda --out speed-cuda.json [--smoke]

- ``act b1`` / ``act b32``: a shipped file as shipped (``--tracker``), on bench_trackers' moving
  observations of the synthetic ``small`` world (batch 32: ``batch_invariant=False``, one
  forward, the batched path), best of 3 passes after a warm-up;
- ``eval``: ``training.evaluate.evaluate`` with 8 sub-envs on the first ``--eval-tracklets``
  test tracklets of the ``small`` world, frames / wall second (env steps included);
- ``finetune``: ``pointtrack finetune --algo group`` of gpt-kitti1-u (head, issue 41's flags:
  group 8, 4 envs, n-steps 64, batch 64, 2 epochs) on the ``tiny`` world, 1,024 env steps on
  CUDA and 256 on the CPU, / wall second of the whole command (start-up included: a floor);
- ``train``: ``benchmarks/bench_training.py`` (P2B slim -U, batch 16), samples/s.

``--smoke``: a tiny version of each (few observations, batch 4, 2 tracklets, 64 steps) to check
the script on a CPU before device time is spent on it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from bench_trackers import moving_observations  # noqa: E402

import trackers  # noqa: E402
from training.evaluate import evaluate, observation_keys_for  # noqa: E402


def act_rates(name: str, device: str, count: int, batch: int) -> dict[str, float]:
    """Frames/s of ``act`` at batch 1 over ``count`` observations and at batch ``batch``."""
    model = trackers.load(name, map_location=device)
    obs = moving_observations(max(count, batch), observation_keys_for([model]))
    stacked = {k: np.stack([o[k] for o in obs[:batch]]) for k in obs[0]}
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)

    def best(fn, frames: int) -> float:
        fn()
        sync()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            fn()
            sync()
            times.append(time.perf_counter() - start)
        return frames / min(times)

    b1 = best(lambda: [model.act(o) for o in obs[:count]], count)
    model.batch_invariant = False  # one forward for the whole batch
    bn = best(lambda: model.act(stacked), batch)
    return {"act b1": b1, f"act b{batch}": bn}


def eval_rate(name: str, device: str, tracklets: int) -> float:
    """Frames / wall second of an 8-env evaluation of the first ``tracklets`` test tracklets."""
    from envs.tracking_env import make_synthetic_env

    model = trackers.load(name, map_location=device)
    model.batch_invariant = not device.startswith("cuda")
    env = make_synthetic_env(
        preset="small",
        split="test",
        setting="kitti-1",
        observation_keys=observation_keys_for([model]),
    )
    chosen = list(range(min(tracklets, env.num_tracklets)))
    frames = sum(env.tracklet_lengths[i] - 1 for i in chosen)
    start = time.perf_counter()
    evaluate(model, env, tracklets=chosen, num_envs=8)
    return frames / (time.perf_counter() - start)


def finetune_rate(device: str, timesteps: int, out: Path) -> float:
    """Env steps / wall second of one ``pointtrack finetune --algo group`` command."""
    cmd = [
        sys.executable, "-m", "training.cli", "finetune", "--tracker", "gpt-kitti1-u",
        "--algo", "group", "--group-size", "8", "--num-envs", "4", "--n-steps", "64",
        "--batch-size", "64", "--n-epochs", "2", "--train-parts", "head", "--preset", "tiny",
        "--timesteps", str(timesteps), "--device", device, "--threads", "1", "--no-val",
        "--no-progress", "--out", str(out), "--overwrite",
    ]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return timesteps / (time.perf_counter() - start)


def train_rate(device: str, batch: int, steps: int) -> float:
    """P2B slim -U samples/s of benchmarks/bench_training.py."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "train.json"
        workers = "4" if device.startswith("cuda") else "0"
        cmd = [
            sys.executable, str(ROOT / "benchmarks" / "bench_training.py"), "--trackers", "p2b",
            "--modes", "none", "--batch", str(batch), "--steps", str(steps), "--repeats", "1",
            "--device", device, "--workers", workers, "--json-out", str(out),
        ]  # fmt: skip
        subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        return json.loads(out.read_text())["p2b-U train"]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--tracker", default="p2b-kitti1-u")
    p.add_argument("--smoke", action="store_true", help="a tiny version of every measurement")
    args = p.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: torch {torch.__version__} sees no CUDA device")
    torch.set_num_threads(1)
    smoke = args.smoke
    results: dict[str, float | str] = {
        "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    }
    results.update(act_rates(args.tracker, args.device, 4 if smoke else 24, 4 if smoke else 32))
    results["eval"] = eval_rate(args.tracker, args.device, 2 if smoke else 16)
    with tempfile.TemporaryDirectory() as tmp:
        steps = 64 if smoke else 1024 if args.device.startswith("cuda") else 256
        results["finetune"] = finetune_rate(args.device, steps, Path(tmp) / "ft")
    results["train"] = train_rate(args.device, 4 if smoke else 16, 1 if smoke else 4)
    tmp_out = Path(args.out).with_suffix(".tmp")
    tmp_out.write_text(json.dumps(results, indent=1))
    tmp_out.replace(args.out)
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
