"""Where a batch-1 ``act`` spends its time: ``torch.profiler`` tables of shipped files.

Usage: ``python benchmarks/profile_act.py [--files p2b-kitti1-u,...] [--observations 24]
[--rows 10] [--threads 1]``: for each file, the profiler's top ``--rows`` ops by self CPU time
over one pass of ``act`` on bench_trackers' moving observations (after a warm-up pass), with the
total per frame.
"""

from __future__ import annotations

import torch
from baseline import parser, use_code_root
from bench_trackers import moving_observations

use_code_root()

import trackers  # noqa: E402
from training.evaluate import observation_keys_for  # noqa: E402


def main() -> int:
    p = parser(__doc__, threads=1, repeats=1)
    p.add_argument("--files", default="p2b-kitti1-u,bat-kitti1-u,gpt-kitti1-u,m2track-kitti1-u")
    p.add_argument("--observations", type=int, default=24)
    p.add_argument("--rows", type=int, default=10)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    models = {name: trackers.load(name) for name in args.files.split(",")}
    observations = moving_observations(
        args.observations, observation_keys_for(list(models.values()))
    )
    for name, model in models.items():
        for obs in observations:  # warm-up (caches, allocator)
            model.act(obs)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            for obs in observations:
                model.act(obs)
        events = prof.key_averages()
        total = sum(e.self_cpu_time_total for e in events) / 1e3 / len(observations)
        calls = sum(e.count for e in events) / len(observations)
        print(f"\n{name}: {total:.2f} ms of ops per frame, {calls:.0f} op calls per frame")
        print(events.table(sort_by="self_cpu_time_total", row_limit=args.rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
