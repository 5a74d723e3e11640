"""Benchmark pretraining throughput on this machine: samples/s of the trainer's own epochs.

Usage: ``python benchmarks/bench_training.py [--quick] [--threads N] [--batch B]
[--trackers p2b,bat,gpt] [--config slim|default] [--device cpu|cuda] [--workers W]
[--data small|toy] [--baseline REV [--rounds 3]]``.

For each tracker and weighting mode (-U plain, -W decorrelation, -S SAM): samples/s of
:meth:`training.pretrain.Trainer.train_epoch` over ``--steps`` steps (sample construction +
forward + loss + backward + optimizer step, exactly ``pointtrack train``'s loop, loader start
included) after a one-step warm-up epoch, best of ``--repeats`` epochs; and the
sample-construction rate of the training samples alone. ``--data small``: the ``small``
synthetic world's kitti-1 training samples (as ``pointtrack train --preset small``); ``toy``:
the env's toy dataset. ``slim`` is the reduced-width configuration the shipped checkpoints use
(the trackers' ``sizes["slim"]``); ``default`` the papers' widths. On CUDA the epochs are
timed to the device's completion; the samples come from ``--workers`` DataLoader processes, as
``pointtrack train --num-workers``. ``--baseline REV`` compares with another commit
(``benchmarks/baseline.py``). The default ``--batch 8`` keeps a run short; ``pointtrack train``'s
default is 48, where CPU training's large activations show (:mod:`training.allocator`).
"""

from __future__ import annotations

import torch
from baseline import best_seconds, parser, run, use_code_root

use_code_root()


def sample_data(kind: str, tracker: str, cfg_kwargs: dict):
    """The training samples of ``--data`` for ``tracker`` (the trainer's own recipe)."""
    from training.config import TrainConfig
    from training.pretrain import default_train_data

    if kind == "toy":
        from envs.tracking_env import make_toy_dataset
        from training.samples import TrackingSamples

        return TrackingSamples(make_toy_dataset(num_frames=16).tracklets, candidates_per_frame=4)
    return default_train_data(TrainConfig(tracker=tracker, preset=kind, **cfg_kwargs).validate())


def main() -> int:
    p = parser(__doc__, threads=1, repeats=2)
    p.add_argument("--quick", action="store_true", help="p2b only, -U and -W, 2 steps")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--trackers", default="p2b,bat,gpt")
    p.add_argument("--config", choices=("slim", "default"), default="slim")
    p.add_argument(
        "--modes", default="none,decorrelation,sam", help="weightings to time (comma-separated)"
    )
    p.add_argument("--recipe", choices=("v1", "v2"), default="v1")
    p.add_argument("--data", choices=("small", "toy"), default="small")
    p.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    p.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    names = ["p2b"] if args.quick else args.trackers.split(",")
    modes = ["none", "decorrelation"] if args.quick else args.modes.split(",")
    steps = 2 if args.quick else args.steps
    print(
        f"training, batch {args.batch}, {args.threads} thread(s), {args.config} widths, "
        f"recipe {args.recipe}, {args.data} data, {args.device}, {args.workers} loader worker(s)"
    )
    return run(args, lambda: measure(args, names, modes, steps), "samples/s")


def measure(args, names: list[str], modes: list[str], steps: int) -> dict[str, float]:
    from training.config import TrainConfig, tracker_config
    from training.pretrain import Trainer

    rates = {}
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else None
    for name in names:
        common = {"recipe": args.recipe, "tracker_config": tracker_config(name, args.config)}
        data = sample_data(args.data, name, common)
        n = min(len(data), 64 if args.quick else 256)
        build = best_seconds(lambda d=data, n=n: [d[i] for i in range(n)], 1, 0, clock=args.clock)
        rates[f"{name} samples built"] = n / build
        for mode in modes:
            cfg = TrainConfig(
                tracker=name,
                weighting=mode,
                batch_size=args.batch,
                epochs=args.repeats + 1,
                iters_per_epoch=steps,
                device=args.device,
                num_workers=args.workers,
                progress=False,
                out="/tmp/pointtrack-bench-training",
                **common,
            ).validate()
            trainer = Trainer(cfg, train_data=data, val_fn=False)
            trainer.train_epoch()  # warm-up
            seconds = best_seconds(
                trainer.train_epoch, args.repeats, warmup=0, sync=sync, clock=args.clock
            )
            tag = {"none": "-U", "decorrelation": "-W", "sam": "-S"}[mode]
            rates[f"{name}{tag} train"] = steps * args.batch / seconds
    return rates


if __name__ == "__main__":
    raise SystemExit(main())
