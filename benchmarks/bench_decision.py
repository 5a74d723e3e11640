"""Benchmark the decision step: batch-1 ``act`` (the shipped still-target test and re-ranking)
against the network alone (``eval_forward``), one torch thread, per shipped file.

The observations are those of ``tests/data/decisions.npz`` on which the file moves (the network
runs: the rows where it holds skip it). Each checkout measures in its own process; with
``--baseline DIR`` (another checkout, e.g. ``git worktree add /tmp/base main``) the two run
interleaved, ``--repeats`` times each, best of them kept, so that both see the same load::

    python -m benchmarks.bench_decision --baseline /tmp/base --repeats 5

prints ms per frame for ``act``, the network and ``act`` without the decision step's tests, the
ratio act / network (issue 41's goal: <= 1.10), the step's share read as (act - plain) / network
and timed alone (``trackers.decision.decide`` on the network's outputs, per the network timed in
the same pass, frame by frame in turn: the steadier reading on a shared machine, since the
difference of two passes carries both passes' noise).
Times are the thread's CPU time (``time.thread_time``; one torch thread does all the work), so
that other processes on a shared machine inflate them less than wall time.
Only the public ``trackers.load`` / ``act`` / ``eval_forward`` are read, so any checkout runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "decisions.npz"
NAMES = ("p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u")

# run in the checkout measured (its own ``trackers``): prints
# {name: [act_ms, net_ms, plain_ms, step_ms, step_net_ms]}
WORKER = """
import json, sys, time
import numpy as np, torch
import trackers
torch.set_num_threads(1)
data, names, inner = np.load(sys.argv[1]), sys.argv[2].split(","), int(sys.argv[3])
keys = ("template", "search", "size", "motion")
out = {}
for name in names:
    model = trackers.load(name)
    rows = np.flatnonzero(data[name + "/kind"] != 0)
    obs = [{k: data["obs_" + k][i] for k in keys} for i in rows]
    batches = [{k: torch.from_numpy(v[None]) for k, v in o.items()} for o in obs]
    def per_frame(step):
        best = float("inf")
        for _ in range(inner):
            start = time.thread_time()
            for i in range(len(obs)):
                step(i)
            best = min(best, (time.thread_time() - start) / len(obs))
        return best * 1e3
    with torch.no_grad():
        per_frame(lambda i: model.act(obs[i]))  # warm-up
        act = per_frame(lambda i: model.act(obs[i]))
        net = per_frame(lambda i: model.eval_forward(batches[i]))
        try:  # the decision step alone, on the network's outputs (checkouts that have it),
            from trackers import decision  # each frame's network and step timed in turn
            rule, paired = model.inference, (float("inf"), float("nan"), float("nan"))
            for _ in range(inner):
                net_s = step_s = 0.0
                for b in batches:
                    start = time.thread_time()
                    outputs = model.eval_forward(b)
                    mid = time.thread_time()
                    decision.decide(model, b, outputs, rule)
                    net_s, step_s = net_s + mid - start, step_s + time.thread_time() - mid
                paired = min(paired, (net_s + step_s, net_s, step_s))
            step, step_net = paired[2] / len(obs) * 1e3, paired[1] / len(obs) * 1e3
        except (ImportError, AttributeError, TypeError):
            step = step_net = float("nan")
        if hasattr(model, "inference"):  # trackers.decision
            model.inference = type(model.inference)()
        else:  # before it: the fields in the architecture config
            model.config.hold_chamfer_m, model.config.rerank_top_k = 0.0, 0
        plain = per_frame(lambda i: model.act(obs[i]))
    out[name] = [act, net, plain, step, step_net]
print(json.dumps(out))
"""


def measure(tree: Path, names: list[str], inner: int) -> dict[str, list[float]]:
    """One worker process in checkout ``tree`` -> ``{name: [act_ms, net_ms, plain_ms,
    step_ms, step_net_ms]}`` (``plain``: ``act`` with the still-target test and the re-ranking
    off; ``step``: ``trackers.decision.decide`` alone on the network's outputs, and
    ``step_net`` the network in the same pass, each frame's two timed in turn so that the
    machine's drift hits both; NaN in a checkout without the step)."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", WORKER, str(DATA), ",".join(names), str(inner)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"bench_decision: the worker in {tree} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, help="another checkout to measure beside this")
    parser.add_argument("--names", default=",".join(NAMES), help="shipped files, comma-separated")
    parser.add_argument("--repeats", type=int, default=3, help="worker runs per checkout")
    parser.add_argument("--inner", type=int, default=3, help="passes over the frames per run")
    args = parser.parse_args(argv)
    if args.baseline is not None and not (args.baseline / "trackers").is_dir():
        parser.error(f"--baseline {args.baseline}: not a pointtrack checkout")
    names = args.names.split(",")
    trees = {"this": ROOT, **({"baseline": args.baseline} if args.baseline else {})}
    best: dict[str, dict[str, list[float]]] = {label: {} for label in trees}
    for _ in range(args.repeats):
        for label, tree in trees.items():  # interleaved: both see the same load
            for name, times in measure(tree, names, args.inner).items():
                old = best[label].get(name, [float("inf")] * 5)
                best[label][name] = [min(a, b) for a, b in zip(old, times, strict=True)]
    print(f"batch-1 act vs network alone, ms/frame, 1 thread, best of {args.repeats} runs")
    print("(plain: act with the hold and the re-ranking off; act-plain: their difference per")
    print(" network; step: the decision step alone, timed on the network's outputs, per network)")
    header = f"{'file':<16} {'checkout':<9} {'act':>7} {'network':>8} {'plain':>7}"
    print(f"{header} {'act/network':>11} {'act-plain':>9} {'step':>6}")
    for name in names:
        for label in trees:
            act, net, plain, step, step_net = best[label][name]
            row = f"{name:<16} {label:<9} {act:7.2f} {net:8.2f} {plain:7.2f}"
            print(f"{row} {act / net:11.3f} {(act - plain) / net:9.3f} {step / step_net:6.3f}")


if __name__ == "__main__":
    main()
