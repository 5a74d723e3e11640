"""Benchmark pretraining throughput on this machine: samples/s of the training step.

Usage: ``python benchmarks/bench_training.py [--quick] [--threads N] [--batch B]
[--trackers p2b,bat,gpt] [--config slim|default] [--device cpu|cuda] [--workers W]``.

Prints, for each tracker and weighting mode (-U plain, -W decorrelation, -S SAM), the samples/s
of full training steps (sample construction from the env's toy dataset + forward + loss +
backward + optimizer step, the trainer's own code path) measured after one warm-up step, and
the sample-construction rate of :class:`training.samples.TrackingSamples` alone. ``slim`` is the
reduced-width configuration the shipped checkpoints use (the trackers' ``sizes["slim"]``);
``default`` the papers' widths. On CUDA the steps are timed to the device's completion and
the samples come from ``--workers`` DataLoader processes, as ``pointtrack train --num-workers``.
"""

from __future__ import annotations

import argparse
import time

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="p2b only, -U and -W, 2 steps")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--trackers", default="p2b,bat,gpt")
    parser.add_argument("--config", choices=("slim", "default"), default="slim")
    parser.add_argument(
        "--modes", default="none,decorrelation,sam", help="weightings to time (comma-separated)"
    )
    parser.add_argument("--recipe", choices=("v1", "v2"), default="v2")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    parser.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from envs.tracking_env import make_toy_dataset
    from training.config import TrainConfig, tracker_config
    from training.pretrain import Trainer
    from training.samples import TrackingSamples, split_batch

    data = TrackingSamples(make_toy_dataset(num_frames=16).tracklets, candidates_per_frame=4)
    n = 64 if args.quick else 256
    t0 = time.perf_counter()
    for i in range(n):
        data[i % len(data)]
    print(
        f"samples: {n / (time.perf_counter() - t0):.0f} samples/s built "
        f"(TrackingSamples on the toy dataset, 1 process)"
    )

    names = ["p2b"] if args.quick else args.trackers.split(",")
    modes = ["none", "decorrelation"] if args.quick else args.modes.split(",")
    steps = 2 if args.quick else args.steps
    print(
        f"training step, batch {args.batch}, {args.threads} thread(s), {args.config} widths, "
        f"recipe {args.recipe}, {args.device}, {args.workers} loader worker(s):"
    )
    for name in names:
        for mode in modes:
            cfg = TrainConfig(
                tracker=name,
                weighting=mode,
                batch_size=args.batch,
                epochs=1,
                recipe=args.recipe,
                iters_per_epoch=steps + 1,
                device=args.device,
                num_workers=args.workers,
                progress=False,
                out="/tmp/pointtrack-bench-training",
                tracker_config=tracker_config(name, args.config),
            ).validate()
            trainer = Trainer(cfg, train_data=data, val_fn=False)
            loader = trainer._loader(0)
            it = iter(loader)
            times = []
            for k in range(steps + 1):
                t = time.perf_counter()
                sample = next(it)
                batch, targets, _ = split_batch(sample, trainer.device)
                out = trainer.net(batch)
                losses = trainer.model.loss(out, targets)
                w = trainer._sample_weights(out)
                loss = trainer._objective(losses, out, targets, w)
                trainer.base_opt.zero_grad()
                loss.backward()
                if trainer.sam is not None:
                    trainer.sam.first_step()
                    out2 = trainer.net(batch)
                    trainer._objective(
                        trainer.model.loss(out2, targets), out2, targets, w
                    ).backward()
                    trainer.sam.second_step()
                else:
                    trainer.base_opt.step()
                trainer.step += 1
                if trainer.device.type == "cuda":
                    torch.cuda.synchronize(trainer.device)
                if k:
                    times.append(time.perf_counter() - t)
            rate = args.batch / (sum(times) / len(times))
            tag = {"none": "-U", "decorrelation": "-W", "sam": "-S"}[mode]
            print(f"  {name}{tag}: {rate:.2f} samples/s")


if __name__ == "__main__":
    main()
