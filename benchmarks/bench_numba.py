"""What the ``fast`` extra buys: batch-1 ``act`` of shipped files with the compiled kernels
(``trackers.kernels``) against the same process with every kernel getter returning ``None``
(the torch paths: the same actions, tested in ``tests/test_ops.py``).

    OMP_NUM_THREADS=1 python benchmarks/bench_numba.py [--names p2b-kitti1-u,...] [--repeats 3]

Observations: those of ``tests/data/decisions.npz`` on which each file moves (as
``bench_decision.py``); process CPU time per ``act``, best of ``--repeats`` passes, the two modes
alternating twice so that drift hits both.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from baseline import best_seconds  # noqa: E402 - same folder

import trackers  # noqa: E402
from trackers import kernels  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "decisions.npz"
GETTERS = (
    "hash_kernel",
    "fps_kernel",
    "ball_kernel",
    "knn_kernel",
    "nearest_kernel",
    "scene_kernel",
    "crop_distance_kernel",
)
KEYS = ("template", "search", "size", "motion")


def act_ms(model: torch.nn.Module, observations: list[dict], repeats: int) -> float:
    """Best-of-``repeats`` CPU milliseconds per ``act`` over ``observations`` (one warm-up
    pass: compilation, BatchNorm folds)."""

    def one_pass() -> None:
        for obs in observations:
            model.act(obs)

    return best_seconds(one_pass, repeats, clock="cpu") / len(observations) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--names", default="p2b-kitti1-u,bat-kitti1-u,gpt-kitti1-u")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    compiled = {name: getattr(kernels, name) for name in GETTERS}
    if any(get() is None for get in compiled.values()):
        raise SystemExit("bench_numba.py: numba is not installed (pip install 'pointtrack[fast]')")
    data = np.load(DATA)
    for name in args.names.split(","):
        model = trackers.load(name)
        rows = np.flatnonzero(data[name + "/kind"] != 0)
        observations = [{k: data["obs_" + k][i] for k in KEYS} for i in rows]
        best = {"numba": float("inf"), "torch": float("inf")}
        for mode in ("numba", "torch") * 2:
            for getter, kernel in compiled.items():
                setattr(kernels, getter, kernel if mode == "numba" else (lambda: None))
            best[mode] = min(best[mode], act_ms(model, observations, args.repeats))
        for getter, kernel in compiled.items():
            setattr(kernels, getter, kernel)
        print(
            f"{name}: act {best['numba']:.2f} ms compiled, {best['torch']:.2f} ms torch "
            f"({best['torch'] / best['numba']:.2f}x)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
